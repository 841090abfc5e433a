"""Alignments: offers checked, one edge per pair, the colony frame the same for every daemon."""

from __future__ import annotations

import math

import numpy as np
import pytest

from colonyd.alignment import Alignments, Edge, edge_from_offer, offer_of
from colonyd.errors import WireError


def _rigid(x: float, y: float, yaw_deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
    t = np.eye(4)
    t[:2, :2] = [[c, -s], [s, c]]
    t[:2, 3] = [x, y]
    return t


def _edge(a: str, b: str, t: np.ndarray, conf: float = 0.9) -> Edge:
    return Edge(a, b, t, conf, 100, 0.02, np.eye(6) * 1e-4, 1.0)


def test_colony_frame_is_the_same_whoever_computes_it():
    # true poses of each agent's frame in a site frame
    site = {
        "a": _rigid(0, 0, 0),
        "b": _rigid(3, 1, 90),
        "c": _rigid(-2, 4, 200),
        "d": _rigid(9, 9, 0),
    }
    rel = {(x, y): np.linalg.inv(site[x]) @ site[y] for x in site for y in site}
    one, two = Alignments(), Alignments()
    one.put(_edge("a", "b", rel["a", "b"]))
    one.put(_edge("c", "b", rel["c", "b"], 0.8))
    two.put(_edge("b", "c", rel["b", "c"], 0.8))  # the same pairs, offered the other way round
    two.put(_edge("b", "a", rel["b", "a"]))
    agents = ["d", "c", "b", "a"]
    f1, f2 = one.colony(agents), two.colony(agents)
    assert f1.root == f2.root == "a" and set(f1.transforms) == {"a", "b", "c"}  # d: not aligned
    for agent in "abc":
        np.testing.assert_allclose(f1.transforms[agent], f2.transforms[agent], atol=1e-9)
        np.testing.assert_allclose(
            f1.transforms[agent], np.linalg.inv(site["a"]) @ site[agent], atol=1e-9
        )
    anchored = one.colony(agents, anchor="c")
    assert anchored.root == "c"
    np.testing.assert_allclose(anchored.transforms["a"], rel["c", "a"], atol=1e-9)


def test_a_more_confident_offer_replaces_a_pair_and_bad_offers_are_refused():
    store = Alignments(max_agents=2)
    store.put(_edge("a", "b", _rigid(1, 0, 0), 0.5))
    store.put(_edge("b", "a", _rigid(-2, 0, 0), 0.9))
    (edge,) = store.edges()
    np.testing.assert_allclose(edge.transform, _rigid(2, 0, 0), atol=1e-12)
    with pytest.raises(WireError, match="at most 2 agents"):
        store.admit(_edge("a", "c", np.eye(4)))
    header = {"origin": "a", "epoch": 1, "seq": 1, "time": 5.0}
    offer = offer_of(_edge("a", "b", _rigid(1.5, -2, 30)), header)
    back = edge_from_offer(offer)
    np.testing.assert_allclose(back.transform, _rigid(1.5, -2, 30), atol=1e-9)
    with pytest.raises(WireError, match=r"expected frames 'a\.odom' -> 'b\.odom'"):
        edge_from_offer(offer.model_copy(update={"target_frame": "map"}))
    with pytest.raises(WireError, match="for another agent"):
        edge_from_offer(offer.model_copy(update={"target": "a", "target_frame": "a.odom"}))


def test_offers_reach_the_colony_frame_and_bad_ones_are_refused(make_colony):
    from colonyd.frames import Sender
    from protocol import Heartbeat
    from protocol.identity import Signer
    from protocol.keyexpr import topic_key

    colony = make_colony("offers")
    colony.add("a", ["synthetic:scans=3,rate=8,points=100,seed=1"])
    colony.wait_converged(30)
    s = colony.session()
    ns = colony.namespace
    p = Sender("p", 1, signer=Signer.generate())  # a peer that aligned a's map to its own
    s.put(
        topic_key(ns, "p", "heartbeat"),
        p.encode(Heartbeat(**p.header(), kind="robot", frame_id="p.odom", identity=p.identity)),
    )
    t = _rigid(2.0, -1.0, 35.0)  # a's frame into p's
    good = offer_of(_edge("p", "a", t), p.header())
    bad_frames = offer_of(_edge("p", "a", t), p.header()).model_copy(update={"source_frame": "map"})
    colony.wait_status(  # the heartbeat introduces p's key first
        lambda rs: any(m["agent"] == "p" for r in rs for m in r["members"]), agents=("a",)
    )
    for offer in (good, bad_frames):
        s.put(topic_key(ns, "p", "align"), p.encode(offer))
    s.put(topic_key(ns, "a", "align"), p.encode(offer_of(_edge("p", "a", t), p.header())))

    def placed(reports: list[dict]) -> bool:
        (report,) = reports
        return "p" in report["colony_frame"]["agents"] and report["metrics"]["rejected"].get(
            "keyexpr", 0
        )

    (report,) = colony.wait_status(placed, 30, agents=("a",))
    frame = report["colony_frame"]
    assert frame["root"] == "a"
    np.testing.assert_allclose(np.array(frame["agents"]["p"]), np.linalg.inv(t), atol=1e-5)
    rejected = report["metrics"]["rejected"]
    assert rejected.get("bad-align", 0) == 1 and rejected.get("keyexpr", 0) == 1, rejected


def test_an_agents_new_estimate_replaces_its_old_one_and_confidence_zero_withdraws_it():
    store = Alignments()
    store.put(_edge("a", "b", _rigid(1, 0, 0), 0.9))
    store.put(_edge("a", "b", _rigid(1.2, 0, 0), 0.6))  # a re-estimated on grown maps
    (edge,) = store.edges()
    np.testing.assert_allclose(edge.transform, _rigid(1.2, 0, 0), atol=1e-12)
    store.put(_edge("b", "a", _rigid(-1.1, 0, 0), 0.7))  # b's own offer for the pair
    (edge,) = store.edges()
    np.testing.assert_allclose(edge.transform, _rigid(1.1, 0, 0), atol=1e-12)  # the surer one
    header = {"origin": "b", "epoch": 1, "seq": 2, "time": 6.0}
    withdrawn = edge_from_offer(offer_of(_edge("b", "a", np.eye(4), 0.0), header))
    store.put(withdrawn)  # b takes its offer back: a's stands
    (edge,) = store.edges()
    np.testing.assert_allclose(edge.transform, _rigid(1.2, 0, 0), atol=1e-12)
    store.put(_edge("a", "b", np.eye(4), 0.0))
    assert store.edges() == [] and set(store.colony(["a", "b"]).transforms) == {"a"}


def test_the_colony_frame_carries_each_alignments_error_to_the_agents_on_its_path():
    from voxel.localisation import frame_error

    cov_b = np.zeros((6, 6))
    cov_b[np.ix_([0, 1, 5], [0, 1, 5])] = np.diag([4e-4, 1e-4, 3e-5])  # b's offer, in b's frame
    t_ba = _rigid(2, -3, 40)
    store = Alignments()
    store.put(Edge("b", "a", t_ba, 0.9, 100, 0.02, cov_b, 1.0))
    store.put(_edge("c", "b", _rigid(1, 1, 0), 0.5))  # c hangs below b
    frame = store.colony(["a", "b", "c"], anchor="a")
    np.testing.assert_allclose(frame.covariance("a"), 0.0)
    # b's frame in a's is the inverse of b's offer: its error, moved into a's frame, by sampling
    rng = np.random.default_rng(2)
    samples = rng.multivariate_normal(np.zeros(3), frame_error.planar(cov_b), 3000)
    base = np.linalg.inv(t_ba)
    seen = [
        frame_error.difference(base, np.linalg.inv(_rigid(*d[:2], math.degrees(d[2])) @ t_ba))
        for d in samples
    ]
    np.testing.assert_allclose(np.cov(np.array(seen).T), frame.covariance("b"), atol=2e-5)
    # c adds its own alignment's error (floored) to b's
    assert np.all(np.diag(frame.covariance("c")) > np.diag(frame.covariance("b")))


def test_an_offer_whose_covariance_is_not_one_still_gives_the_colony_frame_covariances():
    # Finite (the protocol checks that much), but indefinite: -0.06 along x = -y.
    cov = np.zeros((6, 6))
    cov[np.ix_([0, 1, 5], [0, 1, 5])] = [[0.04, 0.1, 0.0], [0.1, 0.04, 0.0], [0.0, 0.0, 1e-4]]
    store = Alignments()
    store.put(Edge("b", "a", _rigid(2, -3, 40), 0.9, 100, 0.02, cov, 1.0))
    frame = store.colony(["a", "b"], anchor="a")
    assert np.linalg.eigvalsh(frame.covariance("b")).min() > -1e-12  # unprojected: -0.002
