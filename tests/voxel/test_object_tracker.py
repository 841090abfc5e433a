"""Object tracker: ids stay with their objects as centroids move; new objects get new ids."""

from __future__ import annotations

import numpy as np
import pytest

from voxel.errors import InputError
from voxel.objects import ObjectCentroid, ObjectTracker, moved


def _obj(cls: int, x: float, y: float) -> ObjectCentroid:
    return ObjectCentroid(
        object_id=0,
        class_id=cls,
        position=np.array([x, y, 0.5]),
        covariance=np.eye(3) * 0.01,
        voxel_count=30,
        probability=0.9,
        time=1.0,
    )


def test_ids_follow_objects_and_new_ones_count_up():
    tracker = ObjectTracker(gate=0.5, first_id=100)
    first = tracker.update([_obj(3, 0.0, 0.0), _obj(3, 2.0, 0.0), _obj(5, 0.1, 0.0)])
    assert [o.object_id for o in first] == [100, 101, 102]
    # the map grows: centroids move a little, order changes, one object is new, one is gone
    again = tracker.update([_obj(5, 0.15, 0.05), _obj(3, 2.2, 0.1), _obj(3, 4.0, 0.0)])
    assert [o.object_id for o in again] == [102, 101, 103]
    # a class never takes another class's id, however close
    assert tracker.update([_obj(4, 2.2, 0.1)])[0].object_id == 104
    assert not moved(again, again, 0.05)
    assert moved(first, again, 0.05)
    nudged = [_obj(5, 0.15, 0.05)]
    nudged = [ObjectCentroid(**{**vars(nudged[0]), "object_id": 102})]
    assert moved(
        nudged,
        [ObjectCentroid(**{**vars(nudged[0]), "position": np.array([0.25, 0.05, 0.5])})],
        0.05,
    )
    with pytest.raises(InputError, match="need gate > 0"):
        ObjectTracker(gate=0.0)
