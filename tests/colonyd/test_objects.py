"""Objects at runtime: a daemon's own object list reaches its peers; hostile lists are refused."""

from __future__ import annotations

import time

import numpy as np

from colonyd.frames import Sender
from plugins.world import get_world
from protocol import ObjectCentroid, Objects
from protocol.identity import Signer
from protocol.keyexpr import topic_key


def test_object_lists_reach_peers_and_hostile_ones_are_refused(make_colony):
    colony = make_colony("objects")
    depth = colony.add(
        "depth",
        ["sim:world=room,agent=depth-1,frames=40,start=world,noise=0"],
        start=False,
        extra=["--resolution", "0.05"],
    )
    depth.env = {"COLONYD_OBJECTS_S": "0.5"}
    depth.start()
    colony.add("b", extra=["--resolution", "0.05"])
    colony.wait_converged(60)
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:
        reports = colony.reports(["depth", "b"])
        own = reports["depth"]["objects"]
        heard = reports["b"]["peer_objects"].get("depth", [])
        if own and sorted(o["id"] for o in heard) == sorted(o["id"] for o in own):
            break
        time.sleep(0.3)
    assert own, reports["depth"]
    assert sorted(o["id"] for o in heard) == sorted(o["id"] for o in own)
    assert reports["depth"]["frame"] == "depth.odom"
    truth = get_world("room").objects()  # evaluation only: the daemon never reads it
    for o in own:
        assert o["class"] not in (1, 2)  # walls and floors are structure, not objects
        err = min(
            np.linalg.norm(np.subtract(o["position"], c))
            for cl, c in truth.values()
            if cl == o["class"]
        )
        assert err < 0.5, (o, err)  # surface voxels only: the centroid leans to the camera
    # hostile lists: on another origin's key, unsigned, too long; none is kept
    s = colony.session()
    ns = colony.namespace
    liar = Sender("liar", 1, signer=Signer.generate())
    item = ObjectCentroid(
        object_id=1, class_id=3, position=(0.0, 0.0, 0.0), voxel_count=5, time=1.0
    )
    frame = liar.encode(Objects(**liar.header(), frame_id="liar.odom", objects=[item]))
    s.put(topic_key(ns, "depth", "objects"), frame)  # liar's frame on depth's key
    s.put(
        topic_key(ns, "liar", "objects"),
        Sender("liar", 1).encode(  # unsigned
            Objects(origin="liar", epoch=1, seq=5, time=1.0, frame_id="liar.odom", objects=[item])
        ),
    )
    s.put(topic_key(ns, "liar", "objects"), frame[:40])  # truncated

    def refused(reports: list[dict]) -> bool:  # all three handled (in order, on one worker)
        rejected = next(r for r in reports if r["agent"] == "b")["metrics"]["rejected"]
        return (
            rejected.get("keyexpr", 0) >= 1
            and rejected.get("identity", 0) >= 1
            and rejected.get("malformed", 0) + rejected.get("truncated", 0) >= 1
        )

    (b,) = (r for r in colony.wait_status(refused, agents=("b",)) if r["agent"] == "b")
    assert "liar" not in b["peer_objects"]
    rejected = b["metrics"]["rejected"]
    assert rejected.get("keyexpr", 0) >= 1 and rejected.get("identity", 0) >= 1, rejected
    assert rejected.get("malformed", 0) + rejected.get("truncated", 0) >= 1, rejected
    assert sorted(o["id"] for o in b["peer_objects"]["depth"]) == sorted(o["id"] for o in own)
