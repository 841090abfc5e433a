"""The paper experiment's choices its command line shows (worlds, lidar-1's range): no imports, so
building the parser loads nothing of the experiment."""

from __future__ import annotations

#: lidar-1's range (m): a short-range 2D LiDAR, like cheap ones. With the sim's 12 m it sees
#: every wall of the office from anywhere and is at 0.02 m alone (docs/LOCALISATION.md).
LIDAR_RANGE = 4.0
#: The sim worlds the experiment runs in: the furnished office (default) and the paper's "relatively
#: sparse environment", the hall (docs/LOCALISATION.md "The sparse hall").
WORLDS = ("office", "hall")
