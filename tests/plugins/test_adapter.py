"""Tests of the adapter registry: built-ins and a separately installed third-party adapter."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from plugins.adapter import GROUP, SensorAdapter, available_adapters, load_adapter
from plugins.errors import AdapterNotFoundError, PluginError


def test_builtins_are_registered_as_entry_points() -> None:
    names = available_adapters()
    for name in ("depth", "lidar2d", "lidar3d", "cctv"):
        assert name in names


@pytest.mark.parametrize(
    ("name", "params"),
    [
        ("depth", {"fov": 1.0}),
        ("lidar2d", {}),
        ("lidar3d", {}),
        ("cctv", {"fov": 1.0}),
    ],
)
def test_builtins_satisfy_the_protocol(name: str, params: dict) -> None:
    adapter = load_adapter(name, **params)
    assert isinstance(adapter, SensorAdapter)
    assert adapter.name == name
    assert adapter.sensor_model.kind == adapter.kind
    assert 0 < adapter.reliability <= 1


def test_unknown_adapter_names_the_known_ones() -> None:
    with pytest.raises(AdapterNotFoundError, match=r"expected one of .*'lidar2d'.*found 'sonarx'"):
        load_adapter("sonarx")


def test_bad_parameters_are_reported() -> None:
    with pytest.raises(
        PluginError, match=r"sensor adapter 'lidar2d': bad parameters \['rnage_max'\]"
    ):
        load_adapter("lidar2d", rnage_max=3.0)


SONAR = '''
"""A third-party sonar adapter for the colony test."""
import numpy as np
from plugins.observation import Observation
from voxel.sensor import SensorModel


class Sonar:
    name = "{name}"
    kind = "unknown"

    def __init__(self, *, cone=0.3):
        self.cone = cone
        self.reliability = 0.5
        self.noise = 0.05
        self.sensor_model = SensorModel(prob_hit=0.6, prob_miss=0.45, max_range=5.0)

    def observe(self, reading, *, pose=None, time=0.0, odometry=None, frame=""):
        r = float(reading)
        return Observation(sensor=self.name, time=time, points=np.array([[r, 0.0, 0.0]]),
                           pose=np.eye(4) if pose is None else pose, frame=frame)
'''


def build_wheel(src: Path, dist: str, module: str, name: str) -> Path:
    """A pure-Python wheel of `module` with one colony.sensors entry point (PEP 427 layout)."""
    import base64
    import hashlib
    import zipfile

    stem = dist.replace("-", "_")
    info = f"{stem}-0.0.1.dist-info"
    files = {
        f"{module}.py": (src / f"{module}.py").read_bytes(),
        f"{info}/METADATA": f"Metadata-Version: 2.1\nName: {dist}\nVersion: 0.0.1\n".encode(),
        f"{info}/WHEEL": (
            b"Wheel-Version: 1.0\nGenerator: colony-test\nRoot-Is-Purelib: true\n"
            b"Tag: py3-none-any\n"
        ),
        f"{info}/entry_points.txt": f"[{GROUP}]\n{name} = {module}:Sonar\n".encode(),
    }
    record = []
    for path, data in files.items():
        digest = base64.urlsafe_b64encode(hashlib.sha256(data).digest()).rstrip(b"=").decode()
        record.append(f"{path},sha256={digest},{len(data)}")
    record.append(f"{info}/RECORD,,")
    files[f"{info}/RECORD"] = ("\n".join(record) + "\n").encode()
    wheel = src / "dist" / f"{stem}-0.0.1-py3-none-any.whl"
    wheel.parent.mkdir()
    with zipfile.ZipFile(wheel, "w") as zf:
        for path, data in files.items():
            zf.writestr(path, data)
    return wheel


def test_third_party_adapter_installed_as_its_own_distribution_is_found(tmp_path: Path) -> None:
    tag = f"{os.getpid()}"
    dist, module, name = f"colony-sonar-test-{tag}", f"colony_sonar_test_{tag}", f"sonar{tag}"
    (tmp_path / f"{module}.py").write_text(SONAR.format(name=name))
    (tmp_path / "pyproject.toml").write_text(
        textwrap.dedent(f"""
        [build-system]
        requires = ["setuptools>=61"]
        build-backend = "setuptools.build_meta"

        [project]
        name = "{dist}"
        version = "0.0.1"

        [project.entry-points."{GROUP}"]
        {name} = "{module}:Sonar"

        [tool.setuptools]
        py-modules = ["{module}"]
    """)
    )
    pip = [sys.executable, "-m", "pip", "--disable-pip-version-check", "-q"]
    built = subprocess.run(
        [*pip, "install", "--no-deps", "--no-build-isolation", str(tmp_path)],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        check=False,
    )
    if built.returncode != 0:
        # an old setuptools without `wheel` cannot build in place: build the same wheel by hand
        assert "bdist_wheel" in built.stderr + built.stdout, built.stderr
        wheel = build_wheel(tmp_path, dist, module, name)
        subprocess.run(
            [*pip, "install", "--no-deps", str(wheel)],
            check=True,
            capture_output=True,
            cwd=tmp_path,
        )
    try:
        probe = textwrap.dedent(f"""
            from plugins.adapter import available_adapters, load_adapter
            assert "{name}" in available_adapters(), available_adapters()
            sonar = load_adapter("{name}", cone=0.5)
            obs = sonar.observe(2.5, time=1.0)
            print(
                type(sonar).__module__, sonar.cone, obs.points.tolist(), sonar.sensor_model.prob_hit
            )
        """)
        done = subprocess.run(
            [sys.executable, "-c", probe], capture_output=True, text=True, cwd=tmp_path, check=False
        )
        assert done.returncode == 0, done.stderr
        assert done.stdout.split() == [module, "0.5", "[[2.5,", "0.0,", "0.0]]", "0.6"]
    finally:
        subprocess.run([*pip, "uninstall", "-y", dist], check=False, capture_output=True)
    after = subprocess.run(
        [sys.executable, "-c", "from plugins.adapter import available_adapters as a; print(a())"],
        capture_output=True,
        text=True,
        check=True,
    )
    assert name not in after.stdout


def test_load_adapter_rejects_objects_that_are_not_adapters(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    from importlib.metadata import EntryPoint

    import plugins.adapter as registry

    fake = EntryPoint(name="notone", value="builtins:dict", group=GROUP)
    monkeypatch.setattr(registry, "adapter_entry_points", lambda: {"notone": fake})
    with pytest.raises(PluginError, match="expected an object with name, kind, sensor_model"):
        load_adapter("notone")
