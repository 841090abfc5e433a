"""Pose graph: what a planar filter fused, step by step, re-solved at once so a later correction
also moves the past poses (the smoothed trajectory SLAM systems output)."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from voxel.errors import LocalisationError
from voxel.localisation import se2

if TYPE_CHECKING:  # scipy.sparse loads where a graph is solved: ~0.3 CPU-s off every start-up
    import scipy.sparse as sp

#: Variance (m^2, rad^2) added to an offset walk's noise: where the filter added none, the two
#: offsets are tied to 1e-5 (m, rad), not left free.
WALK_FLOOR = 1e-10
#: A landmark variable is (x, y, unused): its third component is held at zero by this prior's
#: information (it appears in no edge; without it the normal matrix is singular).
UNUSED_INFORMATION = 1.0


def _wrap(a: np.ndarray) -> np.ndarray:
    out: np.ndarray = np.remainder(a + math.pi, 2.0 * math.pi) - math.pi
    return out


def _rot(yaw: np.ndarray) -> np.ndarray:
    """Rotations (E, 2, 2) of yaws (E,)."""
    c, s = np.cos(yaw), np.sin(yaw)
    return np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)


def _d_rot_t(yaw: np.ndarray, v: np.ndarray) -> np.ndarray:
    """d(R(yaw)^T v)/d yaw (E, 2) for yaws (E,) and vectors (E, 2)."""
    c, s = np.cos(yaw), np.sin(yaw)
    return np.column_stack([-s * v[:, 0] + c * v[:, 1], -c * v[:, 0] - s * v[:, 1]])


def _information(covariance: np.ndarray) -> np.ndarray:
    """Information (..., d, d) of covariances (..., d, d); a singular one's pseudo-inverse."""
    c = np.asarray(covariance, np.float64)
    c = 0.5 * (c + np.swapaxes(c, -1, -2))
    out: np.ndarray = np.linalg.pinv(c, hermitian=True)
    return out


#: A group of linearised edges: its blocks [(variable ids (E,), Jacobians (E, d, 3))], residuals
#: (E, d) and information (E, d, d).
Term = tuple[list[tuple[np.ndarray, np.ndarray]], np.ndarray, np.ndarray]

#: One own-map match: node, keyframe nodes (G,), placed poses (G, 3), weights (G, 3, 3), the
#: matched pose (3,) and its information (3, 3).
_Match = tuple[int, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]


@dataclass
class _Edges:
    """One kind of edge, as lists until the solve stacks them."""

    nodes: list[np.ndarray] = field(default_factory=list)  # per record (E_i, k) variable ids
    values: list[np.ndarray] = field(default_factory=list)  # per record (E_i, ...) measurements
    information: list[np.ndarray] = field(default_factory=list)  # (E_i, d, d)

    def add(self, nodes: np.ndarray, value: np.ndarray, information: np.ndarray) -> None:
        self.nodes.append(np.asarray(nodes, np.int64))
        self.values.append(np.asarray(value, np.float64))
        self.information.append(np.asarray(information, np.float64))

    def stacked(self) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        if not self.nodes:
            return None
        return (
            np.concatenate(self.nodes),
            np.concatenate(self.values),
            np.concatenate(self.information),
        )


@dataclass(frozen=True)
class Smoothed:
    """A solved graph: every step's body pose (N, 3), every offset (M, 3), and the fit's cost
    (sum of squared Mahalanobis residuals) before and after, with the Gauss-Newton iterations
    taken."""

    poses: np.ndarray
    offsets: np.ndarray
    cost_before: float
    cost_after: float
    iterations: int
    #: every keyed landmark's true position (x, y) as solved, in the order first seen (L, 2)
    landmarks: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))


class PoseGraph:
    """A 2D pose graph over a filter's steps: one node per step (the body pose (x, y, yaw)), one
    variable per colony offset, and as edges exactly what the filter fused, with the covariance
    it used:

    - `step`: odometry between consecutive nodes (the increment, in the earlier node's body
      frame, with the motion model's covariance; a step without odometry has its widening);
    - `match`: an own-map match at the newest node against keyframes placed at earlier nodes,
      one edge on the node and those keyframes' nodes, as the filter models it: the matched
      pose is the node moved by the keyframes' errors, each keyframe g weighted by its share
      W_g of the match's information, z = x + sum_g W_g (seen_g - x), where seen_g is where
      the node appears in the map keyframe g was placed in (`relative(keyframe node, node)`
      composed with the pose it was placed at);
    - `colony`: a pose matched against a shared map, through that map's error (its offset, a
      variable with the prior the filter started it with; `walk_offset` starts a new one tied
      to the last by the process noise the filter added);
    - `absolute` (a fix, the first pose's prior) and `landmark` (an object's position seen from
      the newest node): without a key an absolute edge with the sighting's and the landmark's
      covariances; with a key (the filter estimating the landmark's error, counted once) an
      edge on the node and the landmark's true position, a variable with the published
      position and covariance first seen as its prior (widened as the filter widened it), the
      sighting's own covariance on the edge.

    `solve` minimises the sum of squared Mahalanobis residuals by Gauss-Newton on the sparse
    normal equations from the filter's own estimates. With only odometry it returns them; a
    correction at the end moves the whole path by what odometry allows. Reads no reference."""

    def __init__(self, start: np.ndarray, covariance: np.ndarray) -> None:
        self.online: list[np.ndarray] = [np.asarray(start, np.float64).reshape(3).copy()]
        self._odometry = _Edges()
        self._absolute = _Edges()
        # own-map matches by their number of keyframes G: (node, keyframe nodes (G,), placed
        # (G, 3), weights (G, 3, 3), z (3,), information (3, 3))
        self._match: dict[int, list[_Match]] = {}
        self._colony = _Edges()  # nodes (node, offset); values z
        self._offset_prior = _Edges()  # nodes (offset,); values zeros
        self._offset_walk = _Edges()  # nodes (offset before, offset after)
        self._landmark = _Edges()  # nodes (node,); values (seen 2, landmark 2)
        # keyed landmarks: edges on (node, landmark variable), values seen (2,), the sighting's
        # information; the same as independent edges (for a graph without shared variables);
        # per variable its prior (the position first published, the covariance accounted)
        self._keyed = _Edges()
        self._keyed_alone = _Edges()
        self._landmark_keys: dict[int, int] = {}
        self._landmark_prior: list[tuple[np.ndarray, np.ndarray]] = []
        self._keyframes: dict[int, tuple[int, np.ndarray]] = {}
        self.offsets = 0
        self.add_absolute(self.online[0], covariance, node=0)

    @property
    def nodes(self) -> int:
        """Number of steps recorded."""
        return len(self.online)

    def step(self, increment: np.ndarray, covariance: np.ndarray) -> int:
        """A new node, reached from the last by `increment` (dx, dy, dyaw, body frame) with
        `covariance` (3x3, body frame); its id."""
        u = np.asarray(increment, np.float64).reshape(3)
        last = self.nodes - 1
        self.online.append(se2.compose(self.online[-1], u))
        self._odometry.add(np.array([[last, last + 1]]), u[None], _information(covariance)[None])
        return last + 1

    def place(self, pose: np.ndarray) -> None:
        """The filter's estimate of the newest node (the solve starts from it)."""
        self.online[-1] = np.asarray(pose, np.float64).reshape(3).copy()

    def add_keyframe(self, key: int, placed: np.ndarray) -> None:
        """Keyframe `key` was taken at the newest node and placed at `placed` (x, y, yaw)."""
        self._keyframes[int(key)] = (self.nodes - 1, np.asarray(placed, np.float64).reshape(3))

    def add_match(
        self, pose: np.ndarray, covariance: np.ndarray, keys: np.ndarray, information: np.ndarray
    ) -> None:
        """An own-map match fused at the newest node, as the filter fused it
        (`PlanarEkf.update_relative`): the pose (x, y, yaw) in the map with its covariance, from
        keyframes `keys` (G,) giving `information` (G, 3, 3) each; it measures the node moved by
        the keyframes' errors, each weighted by its share of the information: z = x + sum_g W_g
        (seen_g - x). One edge on the node and its keyframes' nodes. Keyframes the graph does
        not know count as placed without error (seen_g = x), as in the filter."""
        keys = np.asarray(keys).reshape(-1)
        info = np.asarray(information, np.float64).reshape(len(keys), 3, 3)
        total = info.sum(axis=0) + 1e-9 * np.eye(3)
        known = [i for i, k in enumerate(keys.tolist()) if int(k) in self._keyframes]
        if not known:
            return
        kf = [self._keyframes[int(keys[i])] for i in known]
        record = (
            self.nodes - 1,
            np.array([n for n, _ in kf], np.int64),
            np.array([placed for _, placed in kf]),
            np.linalg.solve(total[None], info)[known],
            np.asarray(pose, np.float64).reshape(3),
            _information(covariance),
        )
        self._match.setdefault(len(kf), []).append(record)

    def add_absolute(self, pose: np.ndarray, covariance: np.ndarray, node: int = -1) -> None:
        """An absolute measurement of node `node` (default the newest): its pose (x, y, yaw)."""
        n = self.nodes - 1 if node < 0 else node
        z = np.asarray(pose, np.float64).reshape(1, 3)
        self._absolute.add(np.array([[n]]), z, _information(covariance)[None])

    def add_landmark(
        self,
        seen: np.ndarray,
        seen_covariance: np.ndarray,
        landmark: np.ndarray,
        landmark_covariance: np.ndarray,
        yaw: float,
        key: int | None = None,
    ) -> None:
        """A landmark fused at the newest node: seen at `seen` (x, y, body frame), known at
        `landmark` (x, y). Without `key`, as the filter fuses an independent sighting: the
        noise both covariances with the landmark's turned by the filter's heading `yaw` when it
        was fused. With `key`, as the filter fuses a landmark whose error it estimates
        (`PlanarEkf.update_landmark` with a key): the sighting's noise alone, on the node and
        the landmark's true position, whose prior is the position and covariance published at
        its first sighting, widened by a later published covariance's growth (a published
        move keeps the truth: no change)."""
        c, s = math.cos(yaw), math.sin(yaw)
        rt = np.array([[c, s], [-s, c]])
        lm_cov = np.asarray(landmark_covariance, np.float64)
        noise = np.asarray(seen_covariance) + rt @ lm_cov @ rt.T
        value = np.concatenate([np.asarray(seen).reshape(2), np.asarray(landmark).reshape(2)])
        node = np.array([[self.nodes - 1]])
        if key is None:
            self._landmark.add(node, value[None], _information(noise)[None])
            return
        self._keyed_alone.add(node, value[None], _information(noise)[None])
        var = self._landmark_keys.get(int(key))
        if var is None:
            var = self._landmark_keys[int(key)] = len(self._landmark_prior)
            self._landmark_prior.append((value[2:].copy(), 0.5 * (lm_cov + lm_cov.T)))
        else:
            first, accounted = self._landmark_prior[var]
            grown = lm_cov - accounted
            w, v = np.linalg.eigh(0.5 * (grown + grown.T))
            self._landmark_prior[var] = (first, accounted + (v * np.maximum(w, 0.0)) @ v.T)
        info = _information(np.asarray(seen_covariance, np.float64))
        self._keyed.add(np.array([[self.nodes - 1, var]]), value[None, :2], info[None])

    @property
    def landmarks(self) -> int:
        """Number of keyed landmark variables."""
        return len(self._landmark_prior)

    def reset_offset(self, covariance: np.ndarray) -> int:
        """A new shared map's (or alignment's) error: a new offset variable, zero with
        `covariance`; its index."""
        self.offsets += 1
        self._offset_prior.add(
            np.array([[self.offsets - 1]]), np.zeros((1, 3)), _information(covariance)[None]
        )
        return self.offsets - 1

    def walk_offset(self, covariance: np.ndarray, offset: int | None = None) -> int:
        """Offset `offset`'s error (None: the newest offset) grew by `covariance` (process noise
        about the origin): a new offset variable, that one plus the noise; its index."""
        before = self._offset(offset, "walk_offset")
        self.offsets += 1
        pair = np.array([[before, self.offsets - 1]])
        # a direction the noise leaves out is one the error keeps: nearly rigid there
        floored = np.asarray(covariance, np.float64) + WALK_FLOOR * np.eye(3)
        self._offset_walk.add(pair, np.zeros((1, 3)), _information(floored)[None])
        return self.offsets - 1

    def _offset(self, offset: int | None, what: str) -> int:
        if not self.offsets:
            msg = f"pose graph: expected reset_offset() before {what}()"
            raise LocalisationError(msg)
        if offset is None:
            return self.offsets - 1
        if not 0 <= offset < self.offsets:
            msg = f"pose graph: {what}: expected an offset below {self.offsets}, found {offset}"
            raise LocalisationError(msg)
        return offset

    def add_colony(
        self, pose: np.ndarray, covariance: np.ndarray, offset: int | None = None
    ) -> None:
        """A pose (x, y, yaw) measured through an offset (matched against the shared map, or a
        fix through an alignment whose error the filter estimates), fused at the newest node
        through offset `offset` (None: the newest)."""
        pair = np.array([[self.nodes - 1, self._offset(offset, "add_colony")]])
        z = np.asarray(pose, np.float64).reshape(1, 3)
        self._colony.add(pair, z, _information(covariance)[None])

    def edges(self) -> dict[str, int]:
        """How many edges of each kind."""
        kinds = {
            "odometry": self._odometry,
            "absolute": self._absolute,
            "colony": self._colony,
            "landmark": self._landmark,
            "landmark_keyed": self._keyed,
        }
        out = {k: int(sum(len(n) for n in e.nodes)) for k, e in kinds.items()}
        out["match"] = sum(len(g) for g in self._match.values())
        return out

    def solve(self, iterations: int = 20, tolerance: float = 1e-7) -> Smoothed:
        """Every node's body pose (N, 3) minimising the graph's cost, from the filter's
        estimates, the offsets from zero (Gauss-Newton, damped when a step raises the cost)."""
        poses = np.array(self.online)
        n, m = len(poses), self.offsets
        landmarks = np.array([np.append(first, 0.0) for first, _ in self._landmark_prior])
        start = np.concatenate([poses, np.zeros((m, 3)), landmarks.reshape(-1, 3)])

        def linearised(x: np.ndarray) -> tuple[float, sp.csr_matrix, np.ndarray]:
            return self._linearised(x[:n], x[n:])

        x, first, cost, done = gauss_newton(linearised, start, n, iterations, tolerance)
        return Smoothed(x[:n], x[n : n + m], first, cost, done, x[n + m :, :2].copy())

    def _linearised(
        self, poses: np.ndarray, offsets: np.ndarray
    ) -> tuple[float, sp.csr_matrix, np.ndarray]:
        """The cost, normal matrix and gradient (of half the cost) at `poses` and `offsets`
        (the offsets, then the keyed landmarks)."""
        return normal_equations(self.terms(poses, offsets), 3 * (len(poses) + len(offsets)))

    def terms(self, poses: np.ndarray, offsets: np.ndarray, shared: bool = True) -> list[Term]:
        """The graph's edges linearised at `poses` (N, 3) and `offsets` (M + L, 3: the offsets,
        then the keyed landmarks' positions), grouped by kind (`Term`: variable ids, nodes
        first, then offsets from N, then landmarks); without `shared`, no colony edge nor
        offset nor landmark variable, keyed landmarks as independent edges (a joint graph
        models the shared map otherwise, `JointGraph`)."""
        n = len(poses)
        terms: list[Term] = []
        if shared and self._landmark_prior:
            terms.extend(self._keyed_terms(poses, offsets))
        odo = self._odometry.stacked()
        if odo is not None:
            ids, u, info = odo
            a, b = poses[ids[:, 0]], poses[ids[:, 1]]
            e = b[:, :2] - a[:, :2]
            rt = np.swapaxes(_rot(a[:, 2]), 1, 2)
            r = np.column_stack([np.einsum("eij,ej->ei", rt, e), b[:, 2] - a[:, 2]]) - u
            r[:, 2] = _wrap(r[:, 2])
            ja = np.zeros((len(ids), 3, 3))
            ja[:, :2, :2] = -rt
            ja[:, :2, 2] = _d_rot_t(a[:, 2], e)
            ja[:, 2, 2] = -1.0
            jb = np.zeros((len(ids), 3, 3))
            jb[:, :2, :2] = rt
            jb[:, 2, 2] = 1.0
            terms.append(([(ids[:, 0], ja), (ids[:, 1], jb)], r, info))
        absolute = self._absolute.stacked()
        if absolute is not None:
            ids, z, info = absolute
            r = poses[ids[:, 0]] - z
            r[:, 2] = _wrap(r[:, 2])
            terms.append(([(ids[:, 0], np.tile(np.eye(3), (len(ids), 1, 1)))], r, info))
        for group in self._match.values():
            terms.append(_match_term(poses, group))
        colony = self._colony.stacked() if shared else None
        if colony is not None:
            ids, z, info = colony
            x, b = poses[ids[:, 0]], offsets[ids[:, 1]]
            moved = np.einsum("eij,ej->ei", _rot(b[:, 2]), x[:, :2])
            r = np.column_stack([moved + b[:, :2], x[:, 2] + b[:, 2]]) - z
            r[:, 2] = _wrap(r[:, 2])
            jx = np.zeros((len(ids), 3, 3))
            jx[:, :2, :2] = _rot(b[:, 2])
            jx[:, 2, 2] = 1.0
            jb = np.tile(np.eye(3), (len(ids), 1, 1))
            jb[:, 0, 2], jb[:, 1, 2] = -moved[:, 1], moved[:, 0]
            terms.append(([(ids[:, 0], jx), (n + ids[:, 1], jb)], r, info))
        prior = self._offset_prior.stacked() if shared else None
        if prior is not None:
            ids, z, info = prior
            eye = np.tile(np.eye(3), (len(ids), 1, 1))
            terms.append(([(n + ids[:, 0], eye)], offsets[ids[:, 0]] - z, info))
        walk = self._offset_walk.stacked() if shared else None
        if walk is not None:
            ids, _, info = walk
            eye = np.tile(np.eye(3), (len(ids), 1, 1))
            r = offsets[ids[:, 1]] - offsets[ids[:, 0]]
            terms.append(([(n + ids[:, 0], -eye), (n + ids[:, 1], eye)], r, info))
        for kind in (self._landmark, None if shared else self._keyed_alone):
            landmarks = None if kind is None else kind.stacked()
            if landmarks is None:
                continue
            ids, values, info = landmarks
            x = poses[ids[:, 0]]
            d = values[:, 2:] - x[:, :2]
            rt = np.swapaxes(_rot(x[:, 2]), 1, 2)
            r = np.einsum("eij,ej->ei", rt, d) - values[:, :2]
            j = np.zeros((len(ids), 2, 3))
            j[:, :, :2] = -rt
            j[:, :, 2] = _d_rot_t(x[:, 2], d)
            terms.append(([(ids[:, 0], j)], r, info))
        return terms

    def _keyed_terms(self, poses: np.ndarray, extra: np.ndarray) -> list[Term]:
        """The keyed landmarks' sightings (R(yaw)^T (t - position) - seen, on the node and the
        landmark's true position t) and their priors (t - the position first published)."""
        n, m = len(poses), self.offsets
        lms = extra[m:]
        ids, seen, info = self._keyed.stacked() or (np.zeros((0, 2), np.int64), None, None)
        terms: list[Term] = []
        if seen is not None and info is not None:
            x, t = poses[ids[:, 0]], lms[ids[:, 1]]
            d = t[:, :2] - x[:, :2]
            rt = np.swapaxes(_rot(x[:, 2]), 1, 2)
            r = np.einsum("eij,ej->ei", rt, d) - seen
            jx = np.zeros((len(ids), 2, 3))
            jx[:, :, :2] = -rt
            jx[:, :, 2] = _d_rot_t(x[:, 2], d)
            jt = np.zeros((len(ids), 2, 3))
            jt[:, :, :2] = rt
            terms.append(([(ids[:, 0], jx), (n + m + ids[:, 1], jt)], r, info))
        first = np.array([f for f, _ in self._landmark_prior])
        prior = np.zeros((len(first), 3, 3))
        prior[:, :2, :2] = _information(np.array([c for _, c in self._landmark_prior]))
        prior[:, 2, 2] = UNUSED_INFORMATION
        r = lms - np.column_stack([first, np.zeros(len(first))])
        eye = np.tile(np.eye(3), (len(first), 1, 1))
        terms.append(([(n + m + np.arange(len(first)), eye)], r, prior))
        return terms

    def colony_edges(self) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """The colony edges in the order they were added: nodes (E,), matched poses (E, 3) and
        their information (E, 3, 3); None without any."""
        colony = self._colony.stacked()
        if colony is None:
            return None
        ids, z, info = colony
        return ids[:, 0].copy(), z, info


def gauss_newton(
    linearised: Callable[[np.ndarray], tuple[float, sp.csr_matrix, np.ndarray]],
    start: np.ndarray,
    wrapped: int,
    iterations: int = 20,
    tolerance: float = 1e-7,
) -> tuple[np.ndarray, float, float, int]:
    """Minimise a cost over variables (V, 3) from `start` by Gauss-Newton on the sparse normal
    equations `linearised` gives (cost, normal matrix, gradient), damped when a step raises the
    cost; the first `wrapped` variables' third component is an angle (wrapped). The variables,
    the cost before and after, and the iterations taken."""
    import scipy.sparse as sp
    from scipy.sparse.linalg import spsolve

    x = np.asarray(start, np.float64).copy()
    cost, h, g = linearised(x)
    first = cost
    damping = 1e-9
    done = 0
    for done in range(1, iterations + 1):  # noqa: B007 - the count is returned
        scale = h.diagonal()
        step = spsolve((h + sp.diags(damping * scale + 1e-12)).tocsc(), -g)
        dx = np.asarray(step).reshape(-1, 3)
        new = x + dx
        new[:wrapped, 2] = _wrap(new[:wrapped, 2])
        new_cost, new_h, new_g = linearised(new)
        if new_cost > cost * (1 + 1e-12) and damping < 1e6:
            damping *= 10.0
            continue
        small = float(np.abs(dx).max()) < tolerance
        x, cost, h, g = new, new_cost, new_h, new_g
        damping = max(damping / 10.0, 1e-9)
        if small:
            break
    return x, first, cost, done


def _match_term(poses: np.ndarray, group: list[_Match]) -> Term:
    """Own-map matches with the same number G of keyframes: residual x + sum_g W_g
    (seen_g - x) - z (seen_g: where the node appears in keyframe g's map), blocks on the node
    and its G keyframe nodes."""
    node = np.array([g[0] for g in group])
    kfn = np.stack([g[1] for g in group])  # (E, G)
    placed = np.stack([g[2] for g in group])  # (E, G, 3)
    w = np.stack([g[3] for g in group])  # (E, G, 3, 3)
    z = np.stack([g[4] for g in group])
    info = np.stack([g[5] for g in group])
    e_count, g_count = kfn.shape
    k = poses[node]  # (E, 3)
    s = poses[kfn].reshape(-1, 3)  # (E G, 3)
    kk = np.repeat(k, g_count, axis=0)
    pl = placed.reshape(-1, 3)
    e = kk[:, :2] - s[:, :2]
    rt = np.swapaxes(_rot(s[:, 2]), 1, 2)
    rp = _rot(pl[:, 2])
    turn = np.einsum("eij,ejk->eik", rp, rt)
    seen_xy = pl[:, :2] + np.einsum("eij,ej->ei", turn, e)
    diff = np.column_stack([seen_xy - kk[:, :2], _wrap(pl[:, 2] - s[:, 2])])
    ww = w.reshape(-1, 3, 3)
    moved = np.einsum("eij,ej->ei", ww, diff).reshape(e_count, g_count, 3).sum(axis=1)
    r = k + moved - z
    r[:, 2] = _wrap(r[:, 2])
    jk = np.zeros((e_count * g_count, 3, 3))
    jk[:, :2, :2] = turn
    jk[:, 2, 2] = 1.0
    js = np.zeros((e_count * g_count, 3, 3))
    js[:, :2, :2] = -turn
    js[:, :2, 2] = np.einsum("eij,ej->ei", rp, _d_rot_t(s[:, 2], e))
    js[:, 2, 2] = -1.0
    j_node = np.eye(3) + np.einsum("eij,ejk->eik", ww, jk - np.eye(3)).reshape(
        e_count, g_count, 3, 3
    ).sum(axis=1)
    j_keys = np.einsum("eij,ejk->eik", ww, js).reshape(e_count, g_count, 3, 3)
    blocks = [(node, j_node)] + [(kfn[:, g], j_keys[:, g]) for g in range(g_count)]
    return blocks, r, info


def normal_equations(terms: list[Term], size: int) -> tuple[float, sp.csr_matrix, np.ndarray]:
    """Cost sum r^T L r, normal matrix sum J^T L J and gradient sum J^T L r of edge groups, each
    given as its blocks [(variable ids (E,), Jacobians (E, d, 3))], residuals (E, d) and
    information (E, d, d)."""
    import scipy.sparse as sp

    cost = 0.0
    grad = np.zeros(size)
    rows: list[np.ndarray] = []
    cols: list[np.ndarray] = []
    data: list[np.ndarray] = []
    local = np.arange(3)
    for blocks, r, info in terms:
        ids = np.stack([b[0] for b in blocks], 1)  # (E, B)
        jac = np.stack([b[1] for b in blocks], 1)  # (E, B, d, 3)
        lr = np.einsum("eij,ej->ei", info, r)
        cost += float(np.einsum("ei,ei->", r, lr))
        np.add.at(grad, 3 * ids[..., None] + local, np.einsum("ebji,ej->ebi", jac, lr))
        lj = np.einsum("eij,ebjk->ebik", info, jac)
        block = np.einsum("eaji,ebjk->eabik", jac, lj)  # (E, B, B, 3, 3): J_a^T L J_b
        shape = block.shape
        rows.append(
            np.broadcast_to(3 * ids[:, :, None, None, None] + local[:, None], shape).ravel()
        )
        cols.append(np.broadcast_to(3 * ids[:, None, :, None, None] + local, shape).ravel())
        data.append(block.ravel())
    if not data:
        return cost, sp.csr_matrix((size, size)), grad
    h = sp.coo_matrix(
        (np.concatenate(data), (np.concatenate(rows), np.concatenate(cols))), shape=(size, size)
    ).tocsr()
    return cost, h, grad


def variance_components(
    groups: dict[str, list[Term]], others: list[Term], size: int
) -> dict[str, tuple[float, float, int]]:
    """Per group of edges (as weighted in the solve), at a solution: its cost Omega_k (sum of
    squared Mahalanobis residuals), its redundancy r_k = n_k - tr(N^-1 N_k) (N the normal
    matrix of every group and of `others`, N_k the group's part: the residuals' degrees of
    freedom the solve could not absorb) and n_k, its residual components. Omega_k / r_k
    estimates the group's variance factor (Foerstner's a posteriori variance component
    estimate), unbiased where Omega_k / n_k is not when the solve bends to fit the group.
    N^-1 is dense (size^2 floats: an offline graph of a few thousand variables)."""
    everything = [t for terms in groups.values() for t in terms] + others
    _, h, _ = normal_equations(everything, size)
    inverse = np.linalg.inv(h.toarray() + 1e-12 * np.eye(size))
    out: dict[str, tuple[float, float, int]] = {}
    for name, terms in groups.items():
        cost, part, _ = normal_equations(terms, size)
        part = part.tocoo()
        absorbed = float(np.sum(inverse[part.col, part.row] * part.data))  # tr(N^-1 N_k)
        count = int(sum(r.size for _, r, _ in terms))
        out[name] = (cost, count - absorbed, count)
    return out
