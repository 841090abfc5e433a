"""Sensor adapters (depth camera, 2D/3D LiDAR, CCTV) and data sources (sim, replay) feeding voxel grids.

Adapters are registered under the entry-point group ``colony.sensors`` (built-ins: ``depth``,
``lidar2d``, ``lidar3d``, ``cctv``); `plugins.adapter.load_adapter(name, **params)` finds them
and any third-party adapter installed as its own distribution.

Sources are opened from spec strings with `plugins.source.open_source(spec)`:

- ``sim:world=office,agent=lidar-1[,seed=0,frames=100,noise=0.02,drift=0,range_noise=0.01,start=origin,realtime=0]``
  worlds ``room`` and ``office``; agents ``depth-1``, ``lidar-1`` (2D), ``lidar3d-1``, ``cctv-1``
  (and ``cctv-2`` in the office).
- ``replay:PATH[,key=value...]``: a CARMEN log (``.log``/``.log.gz``), a 7-Scenes or TUM RGB-D
  folder, or a ROS 1/2 bag (``[ros]`` extra); options ``format``, ``start``, ``stop``, ``step``,
  ``strict``, and per reader ``poses``/``max_range`` (CARMEN), ``stride``/``max_range`` (RGB-D),
  ``topic``/``odom``/``info``/``max_range`` (ROS).
"""
