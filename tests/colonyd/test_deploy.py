"""The systemd unit verifies, and the example config and router config are valid."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import zenoh

from colonyd.config import load_config

DEPLOY = Path(__file__).resolve().parents[2] / "deploy"


def test_unit_has_the_required_settings():
    text = (DEPLOY / "colonyd.service").read_text()
    for line in (
        "Type=notify",
        "WatchdogSec=",
        "Restart=on-failure",
        "StateDirectory=colonyd",
        "ConfigurationDirectory=colonyd",
        "NoNewPrivileges=yes",
        "ProtectSystem=strict",
        "ExecReload=/bin/kill -HUP $MAINPID",
    ):
        assert line in text


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="systemd-analyze not installed")
def test_systemd_analyze_verify(tmp_path):
    # verify checks that ExecStart exists: point it at this environment's console script.
    script = Path(sys.executable).with_name("colonyd")
    if not script.exists():
        script = Path(shutil.which("colonyd") or "/bin/true")
    unit = tmp_path / "colonyd.service"
    unit.write_text(
        (DEPLOY / "colonyd.service").read_text().replace("/opt/colonyd/bin/colonyd", str(script))
    )
    out = subprocess.run(
        ["systemd-analyze", "verify", str(unit)],
        check=False,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert out.returncode == 0, out.stderr
    assert "colonyd.service" not in out.stderr, out.stderr


def test_example_config_is_valid():
    cfg = load_config(DEPLOY / "colonyd.toml")
    assert cfg.colony == "site-a" and cfg.multicast


def test_ros2_example_config_is_valid():
    pytest.importorskip("rosbags")
    cfg = load_config(DEPLOY / "colonyd-ros2.toml")
    assert cfg.ros2_publish and cfg.sources[0].startswith("ros2:")
    from plugins.source import open_source

    source = open_source(cfg.sources[0])
    assert set(source.topics) == {"scan", "odom", "tf", "tf_static"}


def test_router_config_parses():
    conf = zenoh.Config.from_file(str(DEPLOY / "router.json5"))
    assert '"router"' in conf.get_json("mode")
