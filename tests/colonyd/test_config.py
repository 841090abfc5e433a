"""Config: precedence of flags, environment and TOML; clear errors; dump-config."""

from __future__ import annotations

import subprocess
import sys

import pytest

from colonyd.config import dump_config, load_config, multicast_port
from colonyd.errors import ConfigError


def test_precedence_flags_over_env_over_toml(tmp_path, monkeypatch):
    toml = tmp_path / "c.toml"
    toml.write_text(
        'colony = "file"\nagent_id = "file-agent"\n'
        'publish_hz = 1.0\nconnect = ["tcp/127.0.0.1:1"]\n'
    )
    monkeypatch.setenv("COLONYD_AGENT_ID", "env-agent")
    monkeypatch.setenv("COLONYD_PUBLISH_HZ", "3")
    cfg = load_config(toml, publish_hz=5.0)
    assert cfg.colony == "file"  # only in the file
    assert cfg.agent_id == "env-agent"  # env beats file
    assert cfg.publish_hz == 5.0  # flag beats env
    assert cfg.connect == ["tcp/127.0.0.1:1"]
    assert cfg.key_namespace == "file"


def test_toml_colonyd_table_and_env_config_path(tmp_path, monkeypatch):
    toml = tmp_path / "c.toml"
    toml.write_text('[colonyd]\ncolony = "tabled"\n')
    monkeypatch.setenv("COLONYD_CONFIG", str(toml))
    assert load_config().colony == "tabled"


@pytest.mark.parametrize(
    ("flags", "match"),
    [
        ({"publish_hz": -1}, r"publish_hz: Input should be greater than 0"),
        ({"colony": "bad name!"}, r"colony: .*expected 1-64 characters.*found 'bad name!'"),
        (
            {"connect": ["localhost:7447"]},
            r"connect: expected a Zenoh endpoint like 'tcp/127.0.0.1:7447', "
            r"found 'localhost:7447'$",  # once: not again as the list the field was given
        ),
        (  # Zenoh's own words were "invalid port value", naming neither endpoint nor range
            {"listen": ["tcp/127.0.0.1:99999"]},
            r"listen: expected a Zenoh endpoint with host and port 0-65535 .*found "
            r"'tcp/127.0.0.1:99999'",
        ),
        ({"connect": ["tcp/10.0.0.2"]}, r"host and port 0-65535 .*found 'tcp/10.0.0.2'"),
        (
            {"no_such_option": 1},
            r"no_such_option: expected one of the fields `colonyd dump-config` prints "
            r"\(docs/DAEMON.md\), found unknown field 'no_such_option'",
        ),
        (
            {"resolutoin": 0.05},
            r"resolutoin: expected a known field such as 'resolution', found unknown field",
        ),
        (  # a check across fields: its own message, not the whole configuration as "found"
            {"anchor": "cctv-1", "site_pose": [1.0, 2.0]},
            r"invalid configuration:\n  site_pose: expected 4 numbers .*, found 2$",
        ),
        ({"mode": "client", "multicast": False}, r"client mode needs --connect"),
        (
            {"ros2_map_topic": "/colony map"},
            r"ros2_map_topic: .*expected a ROS 2 topic name such as /scan, found '/colony map'",
        ),
        ({"ros2_frame": "colony/frame"}, r"ros2_frame: .*expected a ROS 2 name"),
        ({"ros2_domain": 300}, r"ros2_domain: Input should be less than or equal to 232"),
        (  # a recording's position is kept by its spec: the second reading resumed the first's
            {"sources": ["replay:/data/run.log", "synthetic:scans=3", "replay:/data/run.log"]},
            r"sources: .*expected each recording once .*found 'replay:/data/run.log' twice",
        ),
    ],
)
def test_invalid_config_says_what_was_expected(flags, match):
    with pytest.raises(ConfigError, match=match):
        load_config(None, **flags)


def test_endpoints_zenoh_takes_are_valid():
    eps = ["tcp/[::1]:7447", "tls/router.site-a.lan:7447", "tcp/0.0.0.0:0", "udp/10.0.0.1:7447"]
    eps.append("tcp/192.168.1.2:7447#iface=eth0")
    assert load_config(None, listen=eps).listen == eps


def test_bad_toml_and_missing_file(tmp_path):
    with pytest.raises(ConfigError, match="does not exist"):
        load_config(tmp_path / "nope.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("colony = \n")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_config(bad)


def test_env_type_error(monkeypatch):
    monkeypatch.setenv("COLONYD_RESOLUTION", "fine")
    with pytest.raises(ConfigError, match=r"resolution: .*found 'fine'"):
        load_config()


def test_unknown_environment_variable_is_an_error(monkeypatch):
    monkeypatch.setenv("COLONYD_PUBLISH_HS", "3")  # ignored silently, it would publish at 2 Hz
    with pytest.raises(
        ConfigError,
        match=r"COLONYD_PUBLISH_HS: expected a known field such as 'publish_hz'.*, found unknown",
    ):
        load_config()


def test_multicast_port_is_per_colony_and_stable():
    assert multicast_port("a") == multicast_port("a")
    assert multicast_port("a") != multicast_port("b")


def test_dump_config_round_trips(tmp_path):
    cfg = load_config(None, colony="round", connect=["tcp/127.0.0.1:9"], multicast=False)
    text = dump_config(cfg)
    path = tmp_path / "dumped.toml"
    path.write_text(text)
    again = load_config(path)
    assert again.model_dump() == cfg.model_dump()


def test_cli_dump_config_and_config_error_exit_code(tmp_path):
    out = subprocess.run(
        [sys.executable, "-m", "colonyd", "dump-config", "--colony", "cli", "--no-multicast"],
        check=False,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert out.returncode == 0, out.stderr
    assert 'colony = "cli"' in out.stdout and "multicast = false" in out.stdout
    bad = subprocess.run(
        [sys.executable, "-m", "colonyd", "dump-config", "--resolution", "-1"],
        check=False,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert bad.returncode == 3
    assert "resolution" in bad.stderr and "greater than 0" in bad.stderr


def test_dump_config_hides_the_colony_key():
    text = dump_config(load_config(None, colony_key="very secret value"))
    assert "very secret value" not in text and "colony_key = " in text


def test_trusted_keys_from_toml_and_dump_config(tmp_path):
    key = "ab" * 32
    toml = tmp_path / "c.toml"
    toml.write_text(f'trust = "list"\n[trusted_keys]\ncctv-1 = "{key}"\n')
    cfg = load_config(toml)
    assert cfg.trust == "list" and cfg.trusted_keys == {"cctv-1": key}
    assert f'trusted_keys = {{"cctv-1" = "{key}"}}' in dump_config(cfg)
    with pytest.raises(ConfigError, match=r"expected 'x''s Ed25519 public key as 64 hex digits"):
        load_config(trusted_keys={"x": "abc"})
    with pytest.raises(ConfigError, match="trust: Input should be 'off', 'tofu' or 'list'"):
        load_config(trust="maybe")


def test_identity_command_prints_a_stable_public_key(tmp_path):
    from protocol.identity import Signer

    cmd = [
        sys.executable,
        "-m",
        "colonyd",
        "identity",
        "--agent-id",
        "r1",
        "--state-dir",
        str(tmp_path),
    ]
    first = subprocess.run(cmd, check=False, capture_output=True, text=True, timeout=60)
    assert first.returncode == 0, first.stderr
    key = tmp_path / "identity.key"
    assert key.stat().st_mode & 0o777 == 0o600
    public = Signer.from_bytes(key.read_bytes()).public.hex()
    assert first.stdout == f'"r1" = "{public}"\n'  # a line for another agent's [trusted_keys]
    again = subprocess.run(cmd, check=False, capture_output=True, text=True, timeout=60)
    assert again.stdout == first.stdout
    key.write_bytes(b"short")
    bad = subprocess.run(cmd, check=False, capture_output=True, text=True, timeout=60)
    assert (
        bad.returncode == 1 and "expected 32 raw Ed25519 private key bytes, found 5" in bad.stderr
    )


def test_an_infinite_query_timeout_is_refused_with_a_clear_error() -> None:
    import pytest
    from pydantic import ValidationError

    from colonyd.config import Config

    with pytest.raises(ValidationError, match="query_timeout_s"):
        Config(query_timeout_s=float("inf"))


def test_every_config_field_has_a_row_in_the_daemons_options_table():
    import re
    from pathlib import Path

    from colonyd.config import Config

    doc = (Path(__file__).resolve().parents[2] / "docs" / "DAEMON.md").read_text()
    named = set()
    for first_cell in re.findall(r"^\| ([^|]+) \|", doc, re.M):
        named |= set(re.findall(r"`([a-z_0-9]+)`", first_cell))
    missing = sorted(set(Config.model_fields) - named)
    assert not missing, (
        f"expected a row in docs/DAEMON.md for every config field, not for {missing}"
    )
