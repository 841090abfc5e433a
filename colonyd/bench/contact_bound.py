"""The most a perfect correction at first contact could do for a robot's ATE (issue 12's bound).

`python -m colonyd.bench.contact_bound DIR... [--contacts 10,15,20,30,40] [--json FILE]`
`python -m colonyd.bench.contact_bound --experiment OUT [--json FILE]`

Each DIR holds a robot's estimated and true trajectories as TUM files (`colonyd localize --out
DIR`: `estimate.tum`, `groundtruth.tum`; or a run of `colonyd experiment paper`:
`lidar-1.estimate.tum`, `lidar-1.groundtruth.tum`). For each contact time c (seconds of path
from the first pose) the robot is given its own estimate before c and its TRUE path after it,
and the spliced path is scored as the experiment scores it (ATE RMSE after the rigid Umeyama
fit, evo's `-a`). The ratio to the estimate's own ATE is the smallest a colony could make it by
correcting the robot online from c on, whatever the peer, in two frames for the truth after c:

- `start`: the robot's own frame from its first pose (where a perfect colony frame puts it when
  the frames are tied at the start);
- `fitted`: the frame that best fits the truth before c onto the estimate before c (where an
  alignment from the robot's own drifted map would put a perfect peer map): the smaller of the
  two in every case measured.

A ratio above the claim's 0.5 at the experiment's contact time says no estimator, however good
its peer, can meet the claim online with contact that late. `--experiment OUT` reads a
`colonyd experiment paper --out OUT` folder: for each sharing run, lidar-1's first contact there
(as seconds of its recorded path) and the bound at that contact on the `lidar-alone` run's
trajectories, beside the ratio the run measured. Truth is read only to evaluate.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from colonyd.bench.files import print_and_append
from voxel.localisation.metrics import absolute_trajectory_error, umeyama
from voxel.rotation import quaternion_to_matrix

#: Contact times (s of path) scored by default.
CONTACTS = (10.0, 15.0, 20.0, 30.0, 40.0)
#: The file pairs a directory may hold, in the order they are looked for.
PAIRS = (
    ("estimate.tum", "groundtruth.tum"),
    ("lidar-1.estimate.tum", "lidar-1.groundtruth.tum"),
)


class ContactBoundError(ValueError):
    """A trajectory directory this bench cannot score."""


def read_tum(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Times (N,), positions (N, 3) and the first pose's rotation (3, 3) of a TUM file."""
    try:
        rows = np.loadtxt(path, ndmin=2, comments="#")
    except (OSError, ValueError) as exc:
        msg = f"{path}: expected a TUM trajectory (time x y z qx qy qz qw), found: {exc}"
        raise ContactBoundError(msg) from exc
    if rows.shape[1] != 8 or len(rows) < 3 or not np.all(np.isfinite(rows)):
        msg = f"{path}: expected >= 3 finite rows of 8 columns, found shape {rows.shape}"
        raise ContactBoundError(msg)
    return rows[:, 0], rows[:, 1:4], quaternion_to_matrix(rows[0, 4:8])


def trajectories(directory: Path) -> tuple[Path, Path]:
    """The estimate and truth TUM files of `directory`."""
    for estimate, truth in PAIRS:
        if (directory / estimate).is_file() and (directory / truth).is_file():
            return directory / estimate, directory / truth
    msg = f"{directory}: expected one of the file pairs {PAIRS}, found none"
    raise ContactBoundError(msg)


def spliced_ratios(
    times: np.ndarray,
    estimate: np.ndarray,
    truth: np.ndarray,
    turn: np.ndarray,
    contacts: tuple[float, ...] = CONTACTS,
) -> dict[str, Any]:
    """ATE alone and, per contact time, the spliced path's ATE over it (`start`, `fitted`);
    `turn` takes the truth's axes onto the estimate's at the first pose."""
    alone = absolute_trajectory_error(truth, estimate).rmse
    path_s = times - times[0]
    in_own = (truth - truth[0]) @ turn.T + estimate[0]
    out: dict[str, Any] = {"ate_alone_m": round(alone, 5), "path_s": round(float(path_s[-1]), 2)}
    for contact in contacts:
        before = path_s < contact
        row: dict[str, float | None] = {"start": None, "fitted": None}
        if before.sum() >= 3 and (~before).any() and alone > 0:
            fitted = umeyama(truth[before], estimate[before]).apply(truth)
            for name, after in (("start", in_own), ("fitted", fitted)):
                spliced = np.where(before[:, None], estimate, after)
                row[name] = round(absolute_trajectory_error(truth, spliced).rmse / alone, 3)
        out[f"{contact:g}"] = row
    return out


def measure(directory: Path, contacts: tuple[float, ...] = CONTACTS) -> dict[str, Any]:
    """One directory's bound."""
    estimate_file, truth_file = trajectories(directory)
    t_est, p_est, r_est = read_tum(estimate_file)
    t_true, p_true, r_true = read_tum(truth_file)
    if len(t_est) != len(t_true) or not np.allclose(t_est, t_true, atol=1e-6):
        msg = (
            f"{directory}: expected the estimate and the truth at the same times, found "
            f"{len(t_est)} and {len(t_true)} poses"
        )
        raise ContactBoundError(msg)
    out = spliced_ratios(t_est, p_est, p_true, r_est @ r_true.T, contacts)
    return {"directory": str(directory), **out}


#: The experiment's runs in which lidar-1 shares, scored against `lidar-alone`.
SHARED_RUNS = ("lidar+depth", "lidar+depth+cctv")
ROBOT = "lidar-1"


def experiment(out: Path) -> dict[str, Any]:
    """The bound at each sharing run's own first contact, with the ratio the run measured."""
    try:
        results = json.loads((out / "results.json").read_text())
        runs = results["runs"]
        alone = runs["lidar-alone"][ROBOT]["ate_rmse_m"]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        msg = (
            f"{out}: expected a `colonyd experiment paper` folder with results.json, found: {exc!r}"
        )
        raise ContactBoundError(msg) from exc
    rows: dict[str, Any] = {}
    for run in SHARED_RUNS:
        metrics = runs.get(run, {}).get(ROBOT, {})
        contact = metrics.get("first_contact_s")
        measured = metrics.get("ate_rmse_m")
        row: dict[str, Any] = {
            "first_contact_s": contact,
            "measured": None if not (measured and alone) else round(measured / alone, 3),
        }
        if contact is not None:
            first = read_tum(trajectories(out / run)[0])[0][0]
            path_s = round(max(contact - first, 1e-3), 2)
            bound = measure(out / "lidar-alone", (path_s,))[f"{path_s:g}"]
            row |= {"contact_path_s": path_s, "bound_start": bound["start"]}
            row["bound_fitted"] = bound["fitted"]
        rows[run] = row
    return {"directory": str(out), "ate_alone_m": alone, "runs": rows}


def _contacts(text: str) -> tuple[float, ...]:
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError as exc:
        raise argparse.ArgumentTypeError(
            f"expected seconds, comma-separated, found {text!r}"
        ) from exc
    if not values or not all(math.isfinite(v) and v > 0 for v in values):
        raise argparse.ArgumentTypeError(f"expected positive seconds, found {text!r}")
    return values


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(prog="python -m colonyd.bench.contact_bound")
    parser.add_argument("directories", type=Path, nargs="*")
    parser.add_argument(
        "--experiment", type=Path, help="a `colonyd experiment paper --out` folder instead of DIRs"
    )
    parser.add_argument(
        "--contacts", type=_contacts, default=CONTACTS, help="seconds of path, comma-separated"
    )
    parser.add_argument("--json", type=Path, help="append the result as one JSON line")
    args = parser.parse_args(argv)
    if bool(args.directories) == bool(args.experiment):
        parser.error("expected trajectory folders or --experiment OUT, one of the two")
    if args.experiment:
        try:
            result = experiment(args.experiment)
        except ContactBoundError as exc:
            parser.error(str(exc))
        print_and_append(result, args.json)
        return result
    try:
        rows = [measure(d, args.contacts) for d in args.directories]
    except ContactBoundError as exc:
        parser.error(str(exc))
    for row in rows:
        cells = "  ".join(
            f"{c:g}s {row[f'{c:g}']['start']}/{row[f'{c:g}']['fitted']}" for c in args.contacts
        )
        print(
            f"{row['directory']}: alone {row['ate_alone_m']:.4f} m; start/fitted x alone: {cells}"
        )
    out = {"contacts_s": list(args.contacts), "runs": rows}
    print_and_append(out, args.json)
    return out


if __name__ == "__main__":
    main()
