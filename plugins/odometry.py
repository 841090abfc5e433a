"""The `odometry_noise=` source option: a named or numeric wheel odometry noise model
(voxel.localisation.odometry)."""

from __future__ import annotations

from plugins.errors import SourceSpecError
from voxel.errors import LocalisationError
from voxel.localisation.odometry import OdometryNoise, parse_noise


def odometry_noise_of(text: str | None) -> OdometryNoise | None:
    """The wheel odometry noise model named by a source option, or None; SourceSpecError when
    unknown."""
    if text is None:
        return None
    try:
        return parse_noise(text)
    except LocalisationError as exc:
        msg = f"odometry_noise: {exc}"
        raise SourceSpecError(msg) from None
