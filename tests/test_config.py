import json
import math
from collections.abc import Callable
from pathlib import Path

import pytest
import yaml

from clothd.cli import main
from clothd.config import Config, load_config, parse_config
from clothd.core.camera_model import CameraModel
from clothd.errors import ConfigError
from clothd.formats import write_camera


def test_defaults_are_valid() -> None:
    cfg = load_config(None)
    assert cfg == Config()
    assert cfg.tracker.mesh.nodes_x == 12 and cfg.taichi.arch == "cpu"


@pytest.mark.parametrize(
    ("text", "names"),
    [
        (
            "tracker: {features: {max_features: 3}}\n",
            ["tracker.features.max_features", "greater than or equal to 10"],
        ),
        ("tracker: {ekf: {meas_sigma_px: -1}}\n", ["tracker.ekf.meas_sigma_px", "greater than 0"]),
        ("tracker: {mesh: {nodes_z: 4}}\n", ["tracker.mesh.nodes_z", "Extra inputs"]),
        ("taichi: {arch: tpu}\n", ["taichi.arch"]),
        (
            "tracker: {physics: {slack_strain: 0.06}}\n",
            ["tracker.physics", "slack_strain (0.06) must be below strain_limit (0.05)"],
        ),
        ("opcua: {endpoint: 'http://127.0.0.1:4840/'}\n", ["opcua.endpoint", "opc.tcp://HOST:PORT/PATH"]),
        ("opcua: {endpoint: 'opc.tcp://127.0.0.1:99999/'}\n", ["opcua.endpoint", "Port out of range"]),
        (
            "opcua: {endpoint: 'opc.tcp://0.0.0.0:4840/clothd/'}\n",
            ["opcua.endpoint", "reachable from other machines", "[Basic256Sha256_SignAndEncrypt]"],
        ),
        (
            "opcua: {endpoint: 'opc.tcp://0.0.0.0:1/', security_policies: [Basic256Sha256_SignAndEncrypt]}",
            ["opcua.endpoint", "set api.token"],
        ),
        ("opcua: {security_policies: [Basic128Rsa15]}\n", ["opcua.security_policies"]),
        ("recording: {format: zip}\n", ["recording.format", "'directory' or 'mcap'"]),
        ("foxglove: {port: 0}\n", ["foxglove.port", "greater than or equal to 1"]),
        ("loop: {compute_threads: 0}\n", ["loop.compute_threads", "greater than or equal to 1"]),
        (
            "control: {flattening: {min_speed_m_s: 0.05}}\n",
            ["control.flattening", "min_speed_m_s (0.05) must not exceed max_speed_m_s"],
        ),
        ("foxglove: {enabled: true, host: 0.0.0.0}\n", ["foxglove.host", "foxglove.allow_remote"]),
        ("- a\n- list\n", ["a mapping"]),
        ("tracker: [unclosed\n", ["not valid YAML", "(line 2, column 1)"]),
    ],
)
def test_bad_config_names_the_key_and_bound(tmp_path: Path, text: str, names: list[str]) -> None:
    path = tmp_path / "c.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError) as err:
        load_config(path)
    for name in names:
        assert name in str(err.value)


def test_an_unreadable_config_is_one_line_naming_why(tmp_path: Path) -> None:
    broken, binary = tmp_path / "broken.yaml", tmp_path / "binary.yaml"
    broken.write_text("loop:\n  tick_hz: [1, 2\n")
    binary.write_bytes(b"\xff\xfeloop: 1\n")
    for path, words in ((broken, "expected ',' or ']'"), (binary, "not UTF-8 text")):
        with pytest.raises(ConfigError) as err:
            load_config(path)
        assert words in str(err.value) and "\n" not in str(err.value)


def test_a_path_that_cannot_be_written_is_one_line_naming_it(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], short_recording: Callable[[str], Path]
) -> None:
    a_file = tmp_path / "c.yaml"
    a_file.write_text("tracker: {model: rigid}\n")
    rec = short_recording("translate")
    assert main(["export", str(rec), "--mcap", str(a_file / "inside.mcap")]) == 2  # a file is no folder
    err = capsys.readouterr().err
    assert err == f"clothd: {a_file}: File exists\n"


def test_foxglove_serves_loopback_unless_told_it_may_serve_other_machines() -> None:
    assert load_config(None).foxglove.host == "127.0.0.1" and not load_config(None).foxglove.enabled
    remote = parse_config({"foxglove": {"enabled": True, "host": "0.0.0.0", "allow_remote": True}})
    assert remote.foxglove.host == "0.0.0.0"


def test_check_config_command(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    good, bad = tmp_path / "good.yaml", tmp_path / "bad.yaml"
    good.write_text("tracker: {model: rigid}\n")
    bad.write_text("tracker: {model: magic}\n")
    assert main(["check-config", str(good)]) == 0
    assert main(["check-config", str(bad)]) == 2
    assert "tracker.model" in capsys.readouterr().err
    assert main(["check-config", str(tmp_path / "missing.yaml")]) == 2


def test_check_config_reads_the_files_it_names(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    camera = tmp_path / "camera.json"
    write_camera(camera, CameraModel.ideal(640, 480, 900.0, 1.0))
    names = tmp_path / "names.yaml"
    names.write_text(
        f"camera: {{calibration: {camera}}}\ncell: {{module_calibration: {tmp_path / 'modules.yaml'}}}\n"
    )
    assert main(["check-config", str(names)]) == 2
    assert "cell.module_calibration: " in (err := capsys.readouterr().err)
    assert "modules.yaml: cannot read a module calibration" in err
    (tmp_path / "modules.yaml").write_text("modules: [{module: 99, reversed: false}]\n")
    assert main(["check-config", str(names)]) == 2
    assert "modules.yaml: modules[0]: needs exactly heading_offset_deg" in capsys.readouterr().err
    camera.write_text("{}")
    (tmp_path / "modules.yaml").unlink()
    names.write_text(f"camera: {{calibration: {camera}}}\n")
    assert main(["check-config", str(names)]) == 2
    assert f"camera.calibration: {camera}: missing key" in capsys.readouterr().err
    picture = tmp_path / "camera-calibration.png"  # the report calibrate writes beside camera.json
    picture.write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(range(256)))
    write_camera(camera, CameraModel.ideal(640, 480, 900.0, 1.0))
    names.write_text(
        f"cameras:\n  - {{source: '0', calibration: {camera}}}\n  - {{source: '1', calibration: {picture}}}\n"
    )
    assert main(["check-config", str(names)]) == 2
    assert f"cameras.1.calibration: {picture}: not a text file" in capsys.readouterr().err
    names.write_text(f"camera: {{calibration: {camera}}}\n")
    assert main(["check-config", str(names)]) == 0
    assert str(camera) in capsys.readouterr().out


def test_shipped_config_yaml_is_the_complete_default() -> None:
    path = Path(__file__).resolve().parent.parent / "config.yaml"
    assert load_config(path) == Config()
    # Complete: every key is written out, not left to its default.
    assert yaml.safe_load(path.read_text()) == Config().model_dump(mode="json")


def test_the_compute_process_gets_the_configured_opencv_threads() -> None:
    from clothd.run import build

    parts = build(parse_config({"loop": {"compute_threads": 1}}))
    assert parts.daemon.compute.spec.opencv_threads == 1
    assert build(Config()).daemon.compute.spec.opencv_threads == 2


# -- cameras -----------------------------------------------------------------------------------------


def test_one_camera_without_a_cameras_list() -> None:
    cfg = parse_config({"camera": {"source": "rtsp://a/s", "calibration": "top.json", "stale_after_s": 2}})
    (only,) = cfg.all_cameras
    assert only.name == "cam0" and only.source == cfg.camera
    assert str(only.source.calibration) == "top.json"


def test_a_cameras_list_shares_camera_settings_and_names_each() -> None:
    cfg = parse_config(
        {
            "camera": {"stale_after_s": 2.5, "reconnect_max_s": 9},
            "cameras": [
                {"source": "0", "calibration": "a.json"},
                {"name": "side", "source": "1", "calibration": "b.json"},
            ],
        }
    )
    first, side = cfg.all_cameras
    assert (first.name, first.source.source, str(first.source.calibration)) == ("cam0", "0", "a.json")
    assert (side.name, side.source.source, str(side.source.calibration)) == ("side", "1", "b.json")
    assert first.source.stale_after_s == side.source.stale_after_s == 2.5
    assert side.source.reconnect_max_s == 9


@pytest.mark.parametrize(
    ("data", "names"),
    [
        (
            {"camera": {"source": "0"}, "cameras": [{"source": "1"}]},
            ["camera.source and cameras are both set", "cameras.N.source", "remove camera.source"],
        ),
        (
            {"camera": {"calibration": "c.json"}, "cameras": [{"source": "1"}]},
            ["camera.calibration and cameras are both set", "remove camera.calibration"],
        ),
        (
            {"camera": {"source": "0", "calibration": "c.json"}, "cameras": [{"source": "1"}]},
            ["camera.calibration and camera.source and cameras are both set"],
        ),
        ({"cameras": []}, ["cameras", "at least 1"]),
        (
            {"cameras": [{"source": str(i), "calibration": "c.json"} for i in range(5)]},
            ["cameras", "at most 4"],
        ),
        ({"cameras": [{"source": "0"}, {"source": "1"}]}, ["cameras.1.calibration", "needs its camera.json"]),
        (
            {"cameras": [{"source": "0"}, {"source": "1", "calibration": "c.json"}]},
            ["cameras.0.calibration", "the first needs its camera.json"],
        ),
        (
            {"cameras": [{"source": str(i), "calibration": "c.json"} for i in range(2)]},
            ["cameras.1.calibration", "c.json is cameras.0's too"],
        ),
        (
            {"cameras": [{"source": "0"}, {"name": "cam0", "source": "1", "calibration": "c.json"}]},
            ["cameras.1.name", "'cam0' is taken"],
        ),
        ({"cameras": [{"name": "a b", "source": "0"}]}, ["cameras.0.name", "pattern"]),
        ({"cameras": [{"calibration": "c.json"}]}, ["cameras.0.source", "Field required"]),
    ],
)
def test_bad_cameras_name_the_keys(data: dict[str, object], names: list[str]) -> None:
    with pytest.raises(ConfigError) as err:
        parse_config(data)
    for name in names:
        assert name in str(err.value)


def test_overrides_keep_a_cameras_list_valid() -> None:
    from clothd.config import first_cameras, with_cameras, with_overrides

    cfg = parse_config(
        {
            "cameras": [
                {"source": "0", "calibration": "a.json"},
                {"name": "side", "source": "1", "calibration": "c.json"},
            ]
        }
    )
    assert [c.name for c in with_overrides(cfg, {"api": {"port": 9000}}).all_cameras] == ["cam0", "side"]
    mono = first_cameras(cfg, 1)
    assert [c.source.source for c in mono.all_cameras] == ["0"]
    with pytest.raises(ConfigError, match="--cameras 3: the configuration has 2"):
        first_cameras(cfg, 3)
    with pytest.raises(ConfigError, match="--cameras 3: the simulated cell has 2"):  # run --sim's cameras
        first_cameras(cfg, 3, "the simulated cell")
    # A single camera's source becomes a list's entry: camera.source is no longer set beside it.
    one = parse_config({"camera": {"source": "5", "stale_after_s": 3}})
    two = with_cameras(
        one, [{"source": "a", "calibration": "a.json"}, {"source": "b", "calibration": "c.json"}]
    )
    assert [c.source.source for c in two.all_cameras] == ["a", "b"]
    assert two.camera.stale_after_s == 3
    assert [c.source.source for c in first_cameras(one, 1).all_cameras] == ["5"]


def test_the_shipped_config_yaml_shows_a_cameras_list_that_loads(tmp_path: Path) -> None:
    """The commented example in config.yaml, uncommented with camera.source/calibration deleted, loads."""
    text = (Path(__file__).resolve().parent.parent / "config.yaml").read_text()
    example = [
        line.removeprefix("# ") for line in text.splitlines() if line.startswith(("# cameras:", "#   - "))
    ]
    assert len(example) == 3
    cfg = parse_config(yaml.safe_load("\n".join(example)))
    assert [c.name for c in cfg.all_cameras] == ["top", "side"]


def test_sim_points_every_camera_of_the_cell_and_cameras_n_keeps_the_first(tmp_path: Path) -> None:
    """`clothd run --sim` on the ready line hwsim serve prints; the shipped config.yaml sets camera.source
    and camera.calibration, which the cell's cameras replace."""
    from clothd.config import first_cameras
    from clothd.run import sim_config

    table = {"modules_x": 12, "modules_y": 6, "pitch_m": 0.075, "module_size_m": 0.065}
    (tmp_path / "table.json").write_text(json.dumps(table))
    ready = {
        "table_json": str(tmp_path / "table.json"),
        "serial": "/tmp/ttyCELL",
        "video_url": "http://127.0.0.1:1/video.mjpg",
        "camera_json": "/tmp/camera.json",
        "cameras": [
            {
                "name": "cam0",
                "video_url": "http://127.0.0.1:1/video/cam0.mjpg",
                "camera_json": "/tmp/cam0.json",
            },
            {
                "name": "cam1",
                "video_url": "http://127.0.0.1:1/video/cam1.mjpg",
                "camera_json": "/tmp/cam1.json",
            },
        ],
    }
    shipped = load_config(Path(__file__).resolve().parent.parent / "config.yaml")
    cfg = sim_config(shipped, ready)
    assert [(c.name, c.source.source, str(c.source.calibration)) for c in cfg.all_cameras] == [
        ("cam0", "http://127.0.0.1:1/video/cam0.mjpg", "/tmp/cam0.json"),
        ("cam1", "http://127.0.0.1:1/video/cam1.mjpg", "/tmp/cam1.json"),
    ]
    assert cfg.stepper.port == "/tmp/ttyCELL" and cfg.camera.stale_after_s == shipped.camera.stale_after_s
    assert (cfg.cell.modules_x, cfg.cell.modules_y) == (12, 6)  # the simulated cell's table
    assert cfg.flow.placement == shipped.flow.placement  # no flow scenario: the configuration's
    flow = sim_config(shipped, {**ready, "placement": {"x_m": 0.2, "y_m": -0.01, "theta_deg": 5.0}})
    assert flow.flow.placement.pose == pytest.approx((0.2, -0.01, math.radians(5.0)))
    assert [c.name for c in first_cameras(cfg, 1).all_cameras] == ["cam0"]
    # An hwsim that lists no cameras serves one.
    (only,) = sim_config(Config(), {k: v for k, v in ready.items() if k != "cameras"}).all_cameras
    assert only.source.source == "http://127.0.0.1:1/video.mjpg"


def test_sim_says_when_it_replaces_the_configurations_cameras() -> None:
    from clothd.run import sim_replaced_cameras

    assert sim_replaced_cameras(Config()) is None
    calibrated = parse_config({"camera": {"calibration": "/etc/clothd/top.json"}})
    assert str(sim_replaced_cameras(calibrated)).endswith("replace camera.calibration")
    streamed = parse_config({"camera": {"source": "rtsp://cam/stream"}})
    assert str(sim_replaced_cameras(streamed)).endswith("replace camera.source")
    listed = parse_config({"cameras": [{"source": "0", "calibration": "/etc/clothd/top.json"}]})
    assert "replace cameras" in str(sim_replaced_cameras(listed))


def test_run_takes_cameras_n(monkeypatch: pytest.MonkeyPatch) -> None:
    import clothd.run

    seen: list[object] = []
    monkeypatch.setattr(
        clothd.run,
        "run",
        lambda cfg, sim, record, cameras, controllers: seen.append((sim, cameras, controllers)) or 0,
    )
    assert main(["run", "--sim", "--cameras", "1"]) == 0
    assert main(["run", "--sim", "compress", "--sim-controllers", "2"]) == 0
    assert seen == [("cell", 1, 1), ("compress", None, 2)]
    with pytest.raises(SystemExit):
        main(["run", "--cameras", "0"])
