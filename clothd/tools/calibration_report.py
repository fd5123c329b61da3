"""What `clothd calibrate` reports: reprojection error overall and per picture, outliers, coverage of the
image, and a picture of the residuals.

- Outlier: a picture whose RMS error exceeds OUTLIER_FACTOR x the median picture's, and OUTLIER_FLOOR_PX
  (below that a picture is good whatever its neighbours do). Outliers are named, not dropped: look at
  the picture (motion blur, a bent board, a reflection), delete it and run again.
- Coverage: the image cut into COVERAGE_COLS columns and as many rows as keep the cells square; a cell
  is covered when a corner of some picture lies in it. Distortion is only measured where corners were:
  an uncovered cell, above all at the image's edge, is a guess.
- The picture (PNG, beside camera.json as NAME-calibration.png): the coverage, corners per cell (cells
  without any hatched red), and every corner's residual as an arrow magnified ARROW_SCALE times, one
  colour per picture.
- Several cameras (clothd/tools/calibrate_cameras.py): each camera's report as above, its position in the
  table frame, each pair's epipolar error (median and p95, px), and the `cameras:` entries for the
  configuration. The JSON keeps the first camera's report at its top level, as for one camera, and adds
  `cameras` (each camera's) and `pairs`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from clothd.tools.calibrate import Calibration
from clothd.tools.calibrate_cameras import Rig

OUTLIER_FACTOR = 3.0
OUTLIER_FLOOR_PX = 0.5
COVERAGE_COLS = 8
ARROW_SCALE = 200.0


def coverage_counts(pixels: list[np.ndarray], width: int, height: int) -> np.ndarray:
    """Corners per cell, (rows, COVERAGE_COLS), from each picture's corner pixels (n, 2)."""
    rows = max(1, round(COVERAGE_COLS * height / width))
    counts = np.zeros((rows, COVERAGE_COLS), dtype=int)
    for px in pixels:
        col = np.clip((px[:, 0] + 0.5) * COVERAGE_COLS / width, 0, COVERAGE_COLS - 1).astype(int)
        row = np.clip((px[:, 1] + 0.5) * rows / height, 0, rows - 1).astype(int)
        np.add.at(counts, (row, col), 1)
    return counts


def coverage_map(counts: np.ndarray) -> list[str]:
    """One line per row of cells: '#' covered, '.' not."""
    return ["".join("#" if n else "." for n in row) for row in counts]


def outliers(cal: Calibration) -> list[str]:
    rms = np.array([v.rms_px for v in cal.views])
    bar = max(OUTLIER_FACTOR * float(np.median(rms)), OUTLIER_FLOOR_PX)
    return [v.name for v in cal.views if v.rms_px > bar]


def report_json(cal: Calibration) -> dict[str, Any]:
    cam = cal.camera
    counts = coverage_counts([v.pixels for v in cal.views], cam.width, cam.height)
    named = set(outliers(cal))
    return {
        "rms_px": cal.rms_px,
        "views_used": len(cal.views),
        "image_size_px": [cam.width, cam.height],
        "fx_px": float(cam.K[0, 0]),
        "fy_px": float(cam.K[1, 1]),
        "cx_px": float(cam.K[0, 2]),
        "cy_px": float(cam.K[1, 2]),
        "dist": cam.dist.tolist(),
        "flat": {"name": cal.flat.name, "corners": len(cal.flat.pixels), "rms_px": cal.flat.rms_px},
        "camera_height_m": float(cam.centre_m[2]),
        "views": [
            {
                "name": v.name,
                "corners": len(v.pixels),
                "rms_px": v.rms_px,
                "max_px": float(np.linalg.norm(v.residual_px, axis=1).max()),
                "outlier": v.name in named,
            }
            for v in cal.views
        ],
        "outliers": sorted(named),
        "skipped": [{"name": name, "reason": reason} for name, reason in cal.skipped],
        "coverage": {
            "cells_covered": int(np.count_nonzero(counts)),
            "cells": int(counts.size),
            "corners_per_cell": counts.tolist(),
        },
    }


def format_report(cal: Calibration) -> str:
    r = report_json(cal)
    k = r["dist"]
    lines = [
        f"{r['views_used']} views, RMS reprojection error {r['rms_px']:.3f} px",
        f"fx {r['fx_px']:.2f}  fy {r['fy_px']:.2f}  cx {r['cx_px']:.2f}  cy {r['cy_px']:.2f} px",
        f"k1 {k[0]:.5f}  k2 {k[1]:.5f}  p1 {k[2]:.5f}  p2 {k[3]:.5f}  k3 {k[4]:.5f}",
        f"table: {r['flat']['name']} fits to {r['flat']['rms_px']:.3f} px RMS; "
        f"camera {r['camera_height_m']:.4f} m above it",
        "",
        f"{'picture':<24} {'corners':>7} {'rms px':>7} {'max px':>7}",
    ]
    for v in r["views"]:
        flag = "  outlier" if v["outlier"] else ""
        lines.append(f"{v['name']:<24} {v['corners']:>7} {v['rms_px']:7.3f} {v['max_px']:7.3f}{flag}")
    for s in r["skipped"]:
        lines.append(f"{s['name']:<24} not used: {s['reason']}")
    cov = r["coverage"]
    short = cov["cells_covered"] < cov["cells"]
    hint = (
        " (the lens is extrapolated over the empty ones: add pictures with the board there)" if short else ""
    )
    lines += ["", f"coverage: {cov['cells_covered']} of {cov['cells']} cells{hint}"]
    lines += ["  " + row for row in coverage_map(np.array(cov["corners_per_cell"]))]
    if r["outliers"]:
        lines.append(f"outliers (RMS over {OUTLIER_FACTOR:g} x the median): {', '.join(r['outliers'])}")
    return "\n".join(lines)


def _view_from_vertical_deg(cal: Calibration) -> float:
    """The angle between the camera's optical axis and the table's downward normal."""
    axis_world = cal.camera.T_cam_world[2, :3]  # the camera's z in the table frame
    return float(np.degrees(np.arccos(np.clip(-axis_world[2], -1.0, 1.0))))


def rig_report_json(rig: Rig, outs: list[Path]) -> dict[str, Any]:
    """The first camera's report_json, with `cameras` (every camera's, named, with its camera.json, its
    picture and its position) and `pairs` (each pair's epipolar error)."""
    cameras = [
        {
            "name": name,
            "camera_json": str(out),
            "picture": str(picture_path(out)),
            "position_m": cal.camera.centre_m.tolist(),
            "view_from_vertical_deg": _view_from_vertical_deg(cal),
        }
        | report_json(cal)
        for name, cal, out in zip(rig.names, rig.calibrations, outs, strict=True)
    ]
    pairs = [
        {
            "cameras": list(p.cameras),
            "corners": len(p.distances_px) // 2,
            "epipolar_median_px": p.median_px,
            "epipolar_p95_px": p.p95_px,
        }
        for p in rig.pairs
    ]
    return report_json(rig.calibrations[0]) | {
        "cameras": cameras,
        "pairs": pairs,
        "views_shared": rig.views_shared,
    }


def format_rig_report(rig: Rig, outs: list[Path]) -> str:
    """Each camera's report under its name, then the pairs' epipolar errors and the `cameras:` entries."""
    r = rig_report_json(rig, outs)
    lines: list[str] = []
    for cam, cal in zip(r["cameras"], rig.calibrations, strict=True):
        x, y, z = cam["position_m"]
        lines += [
            f"== {cam['name']}: at ({x:.4f}, {y:.4f}, {z:.4f}) m, "
            f"{cam['view_from_vertical_deg']:.2f}° from vertical",
            format_report(cal),
            "",
        ]
    lines.append(f"{r['views_shared']} held views seen by two cameras or more")
    for p in r["pairs"]:
        a, b = p["cameras"]
        lines.append(
            f"epipolar error {a}-{b}: median {p['epipolar_median_px']:.3f} px, "
            f"p95 {p['epipolar_p95_px']:.3f} px over {p['corners']} corners seen by both"
        )
    lines += ["", "cameras:  # for the configuration (config.yaml); each source is yours to fill in"]
    lines += [
        f"  - {{name: {c['name']}, source: SOURCE, calibration: {c['camera_json']}}}" for c in r["cameras"]
    ]
    return "\n".join(lines)


def picture_path(camera_json: Path) -> Path:
    return camera_json.with_name(f"{camera_json.stem}-calibration.png")


def plot_report(cal: Calibration, path: Path) -> None:
    """Coverage (corners per cell) and the residuals, magnified, over the image frame."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Rectangle

    w, h = cal.camera.width, cal.camera.height
    counts = coverage_counts([v.pixels for v in cal.views], w, h)
    fig, (ax_cov, ax_res) = plt.subplots(1, 2, figsize=(12, 4.8), dpi=100)
    shown = ax_cov.imshow(counts, extent=(-0.5, w - 0.5, h - 0.5, -0.5), cmap="Greens", vmin=0)
    cell_w, cell_h = w / counts.shape[1], h / counts.shape[0]
    for row, col in zip(*np.nonzero(counts == 0), strict=True):  # uncovered: hatched red
        corner = (col * cell_w - 0.5, row * cell_h - 0.5)
        ax_cov.add_patch(Rectangle(corner, cell_w, cell_h, fill=False, hatch="xx", edgecolor="red", lw=0))
    for v in cal.views:
        ax_cov.plot(v.pixels[:, 0], v.pixels[:, 1], ".", color="k", markersize=2)
    fig.colorbar(shown, ax=ax_cov, label="corners per cell")
    ax_cov.set_title(f"coverage: {np.count_nonzero(counts)} of {counts.size} cells")
    for i, v in enumerate(cal.views):
        d = v.residual_px * ARROW_SCALE
        ax_res.quiver(
            v.pixels[:, 0], v.pixels[:, 1], d[:, 0], d[:, 1],
            color=f"C{i % 10}", angles="xy", scale_units="xy", scale=1.0, width=0.002,
        )  # fmt: skip
    ax_res.set_title(f"residuals x{ARROW_SCALE:g} (RMS {cal.rms_px:.3f} px, {len(cal.views)} views)")
    for ax in (ax_cov, ax_res):
        ax.set_xlim(-0.5, w - 0.5)
        ax.set_ylim(h - 0.5, -0.5)
        ax.set_aspect("equal")
        ax.set_xlabel("u, px")
        ax.set_ylabel("v, px")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
