"""`clothd bench robustness`: the tracker on hard footage (periodic weaves, fast belts), graded as bench
accuracy grades.

Two sets of hwsim scenarios (docs/scenarios.md, "Weaves and fast belts"):
- weaves: a strictly periodic plain twill with a relief, under low side light, turned both ways and
  pushed off centre, and a strictly periodic gingham check carried and pushed more than half its period
  a frame; bar (each scenario): feature mean <= 0.3 px, worst <= 1.5 px, node RMSE <= 2 mm;
- fast: every module carrying the denim at 50 to 400 mm/s, a 12 ms exposure with motion blur and heavy
  sensor noise; bar: mean <= 0.5 px and node RMSE <= 2 mm at every speed up to 200 mm/s (300 and 400
  show where accuracy gives out). How accuracy falls with speed
  is printed as a table and drawn as a plot.

The grading is bench_accuracy.grade's, unchanged: feature error against each feature's true pixel, node
error against the true material point in 3-D.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path

from clothd.tools.bench_accuracy import AccuracyRow

WEAVES = ("twill-turn-left", "twill-turn-right", "twill-push", "twill-spin", "gingham-fast", "gingham-push")
FAST = ("fast-050", "fast-100", "fast-150", "fast-200", "fast-300", "fast-400")
SETS = {"weaves": WEAVES, "fast": FAST}


@dataclass(frozen=True)
class Bar:
    mean_px: float
    worst_px: float | None
    node_rmse_mm: float
    up_to_mm_s: float | None = None  # the bar holds up to this belt speed; faster runs show the limit


BARS = {"weaves": Bar(0.3, 1.5, 2.0), "fast": Bar(0.5, None, 2.0, 200.0)}


@dataclass(frozen=True)
class SpeedCase:
    """What a fast-* scenario asks of the camera: belt speed, image motion per frame and blur length."""

    speed_mm_s: float
    px_per_frame: float
    blur_px: float


def set_of(scenario: str) -> str | None:
    return next((name for name, members in SETS.items() if scenario in members), None)


def meets(row: AccuracyRow) -> bool | None:
    """Whether a row meets its set's bar (None: the scenario is in no set, or beyond the bar's speeds)."""
    which = set_of(row.scenario)
    if which is None:
        return None
    bar = BARS[which]
    if bar.up_to_mm_s is not None and speed_case(row.scenario).speed_mm_s > bar.up_to_mm_s + 1e-6:
        return None
    ok = row.feat_mean_px <= bar.mean_px and row.lost_frames == 0
    if bar.worst_px is not None:
        ok &= row.feat_worst_px <= bar.worst_px
    return bool(ok and row.node_rmse_mm is not None and row.node_rmse_mm <= bar.node_rmse_mm)


def speed_case(scenario: str) -> SpeedCase:
    """The fastest commanded belt speed of a scenario, in image terms (its camera straight above)."""
    from hwsim import scenario as scenarios

    sc = scenarios.load(scenario)
    speed = max((c.speed_m_s for c in sc.timeline), default=0.0)
    px_per_m = sc.camera.f_px / sc.camera.position_m[2]
    return SpeedCase(speed * 1e3, speed * px_per_m / sc.fps, speed * px_per_m * sc.noise.exposure_s)


def format_table(rows: list[AccuracyRow]) -> str:
    head = f"{'scenario':<17} {'mode':<8} {'feat mean':>9} {'worst':>7} {'node rmse':>9} {'max':>8}"
    out = [f"{head} {'lost':>4}  bar"]
    for r in rows:
        verdict = {True: "met", False: "NOT met", None: "-"}[meets(r)]
        rmse = f"{r.node_rmse_mm:6.2f} mm" if r.node_rmse_mm is not None else f"{'-':>9}"
        nmax = f"{r.node_max_mm:5.2f} mm" if r.node_max_mm is not None else f"{'-':>8}"
        out.append(
            f"{r.scenario:<17} {r.mode:<8} {r.feat_mean_px:6.3f} px {r.feat_worst_px:7.2f} {rmse} {nmax} "
            f"{r.lost_frames:>4}  {verdict}"
        )
    return "\n".join(out)


def format_speed_table(rows: list[AccuracyRow], mode: str) -> str:
    out = [
        f"{'speed':>9} {'px/frame':>8} {'blur':>7} {'feat mean':>9} {'worst':>7} {'node rmse':>9}  bar "
        f"({mode}, 30 fps, 12 ms exposure)"
    ]
    for r in rows:
        if r.mode != mode or set_of(r.scenario) != "fast":
            continue
        c = speed_case(r.scenario)
        rmse = f"{r.node_rmse_mm:6.2f} mm" if r.node_rmse_mm is not None else f"{'-':>9}"
        verdict = {True: "met", False: "NOT met", None: "beyond the bar"}[meets(r)]
        out.append(
            f"{c.speed_mm_s:5.0f} mm/s {c.px_per_frame:8.2f} {c.blur_px:4.2f} px {r.feat_mean_px:6.3f} px "
            f"{r.feat_worst_px:7.2f} {rmse}  {verdict}"
        )
    return "\n".join(out)


def plot_speed(rows: list[AccuracyRow], path: Path) -> None:
    """Feature mean and worst error (px, left) and node RMSE (mm, right) against belt speed, per mode,
    with the fast-belt bars."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7.5, 4.2), dpi=110)
    right = ax.twinx()
    modes = list(dict.fromkeys(r.mode for r in rows if set_of(r.scenario) == "fast"))
    for i, mode in enumerate(modes):
        sel = [r for r in rows if r.mode == mode and set_of(r.scenario) == "fast"]
        speeds = [speed_case(r.scenario).speed_mm_s for r in sel]
        colour = f"C{i}"
        ax.plot(speeds, [r.feat_mean_px for r in sel], "o-", color=colour, label=f"{mode}: feature mean (px)")
        worst = [r.feat_worst_px for r in sel]
        ax.plot(speeds, worst, "o--", color=colour, alpha=0.5, label=f"{mode}: worst (px)")
        right.plot(
            speeds,
            [r.node_rmse_mm if r.node_rmse_mm is not None else float("nan") for r in sel],
            "s:",
            color=colour,
            label=f"{mode}: node RMSE (mm)",
        )
    ax.axhline(BARS["fast"].mean_px, color="k", linewidth=0.8, linestyle="-.", label="bar: mean 0.5 px")
    rmse_bar = BARS["fast"].node_rmse_mm
    right.axhline(rmse_bar, color="grey", linewidth=0.8, linestyle=":", label="bar: RMSE 2 mm")
    ax.set_xlabel("belt speed, mm/s (30 fps, 12 ms exposure, noise sigma 6)")
    ax.set_ylabel("feature error vs truth, px")
    right.set_ylabel("node RMSE, mm")
    ax.set_ylim(bottom=0)
    right.set_ylim(bottom=0)
    ax.grid(True, alpha=0.3)
    handles = ax.get_legend_handles_labels()
    handles_r = right.get_legend_handles_labels()
    ax.legend(handles[0] + handles_r[0], handles[1] + handles_r[1], fontsize=7, loc="upper left")
    ax.set_title("Fast belts: accuracy against belt speed")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def rows_json(rows: list[AccuracyRow]) -> list[dict[str, object]]:
    out = []
    for r in rows:
        d: dict[str, object] = asdict(r)
        d["set"] = set_of(r.scenario)
        d["meets_bar"] = meets(r)
        if set_of(r.scenario) == "fast":
            d.update(asdict(speed_case(r.scenario)))
        out.append(d)
    return out
