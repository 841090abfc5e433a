"""Sensor adapters (depth camera, 2D/3D LiDAR, CCTV) and every data source feeding voxel grids.

Adapters are registered under the entry-point group ``colony.sensors`` (built-ins: ``depth``,
``lidar2d``, ``lidar3d``, ``cctv``); `plugins.adapter.load_adapter(name, **params)` finds them
and any third-party adapter installed as its own distribution.

Sources (``sim:``, ``replay:``, ``synthetic:``, ``bulk:``) are opened from spec strings with
`plugins.source.open_source(spec)`; their options are pydantic models, listed by
`plugins.source.describe_sources()` (``colonyd sources``, docs/SOURCES.md).
"""
