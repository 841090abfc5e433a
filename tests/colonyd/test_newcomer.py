"""What a newcomer hits first: clear errors, never a traceback, and the documented exit codes."""

from __future__ import annotations

import os
import subprocess
import sys


def _colonyd(*args: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "colonyd", *args],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
        env={**os.environ, **(env or {})},
    )


def test_version_and_clear_config_errors(tmp_path):
    version = _colonyd("--version")
    assert version.returncode == 0 and version.stdout.startswith("colonyd ")
    bad_env = _colonyd("dump-config", env={"COLONYD_CONNECT": "tcp/127.0.0.1:1"})
    assert bad_env.returncode == 3 and "Traceback" not in bad_env.stderr
    assert "COLONYD_CONNECT: expected JSON" in bad_env.stderr
    (tmp_path / "file").write_text("x")
    out_file = _colonyd(
        "map", "--source", "sim:world=room,agent=lidar-1,frames=1", "--out", str(tmp_path / "file")
    )
    assert (
        out_file.returncode == 3 and "--out: expected a directory, found a file" in out_file.stderr
    )
    export_dir = _colonyd(
        "run",
        "--agent-id",
        "a",
        "--state-dir",
        str(tmp_path / "s"),
        "--no-multicast",
        "--export-dir",
        str(tmp_path / "file"),
    )
    assert export_dir.returncode == 3 and "export_dir: expected a directory" in export_dir.stderr


def test_map_of_a_source_whose_every_frame_fails_is_an_error(tmp_path):
    log = tmp_path / "bad.log"
    log.write_text("FLASER 3 1.0 2.0\nFLASER x y z\n")
    run = _colonyd("map", "--source", f"replay:{log},format=carmen", "--out", str(tmp_path / "o"))
    assert run.returncode == 4, run.stderr
    assert "expected at least one readable frame, found none (2 skipped" in run.stderr
    assert not (tmp_path / "o" / "map.bt").exists()
