from pathlib import Path

import pytest
import yaml

from clothd.cli import main
from clothd.config import Config, load_config, parse_config
from clothd.errors import ConfigError


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
        ("tracker: [unclosed\n", ["not valid YAML"]),
    ],
)
def test_bad_config_names_the_key_and_bound(tmp_path: Path, text: str, names: list[str]) -> None:
    path = tmp_path / "c.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError) as err:
        load_config(path)
    for name in names:
        assert name in str(err.value)


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
