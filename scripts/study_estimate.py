"""The a-posteriori estimate (accuracy.py) against the full-order truth on the paper's beam.

    python scripts/study_estimate.py TRUTH_DIR [-o OUT.csv] [--modes 4,6,10,20,40] [--rtol 1e-6,1e-4]
                                       [--enrichment dbf,none]

TRUTH_DIR holds the full-order truths of scripts/study_accuracy.py (truth-<constraints>-400-2.5e-06-0.2.h5:
400 elements, 2.5 us steps, 0.2 s, samples every 1e-4 s, made by `study_accuracy.py -o DIR`, in DIR/runs).
Each case is a reduced run of jobs/paper_beam*.toml (1, 4, 9 stops) to 0.2 s with the estimate over
[0, 0.2] s; the true error is the estimate's own measure against the truth (accuracy.relative_difference:
the largest |w - w_truth| at any constraint over the largest |w_truth| at any constraint). Serial; each
case is a run of under a second. scripts/study_accuracy.py --grid control measures the same over the
truths' trusted horizons, on the tube too.
"""
import argparse
import csv
import os
import sys
import tempfile

import h5py
import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

from dbf_hpc.accuracy import relative_difference  # noqa: E402
from dbf_hpc.errors import DbfError  # noqa: E402
from dbf_hpc.run import run  # noqa: E402
from dbf_hpc.scene import load_scene  # noqa: E402

SCENES = {1: "paper_beam.toml", 4: "paper_beam_4.toml", 9: "paper_beam_9.toml"}
T_END, SAMPLE_DT = 0.2, 1e-4   # s: the truths' span and sampling, and every case's


def truth_path(truth_dir: str, label: int) -> str:
    return os.path.join(truth_dir, f"truth-{label}-400-2.5e-06-0.2.h5")


def read_truth(truth_dir: str, label: int) -> np.ndarray:
    """The truth's constraint displacements, once checked to be the truth of this question: the
    scene's number of stops, sampled every SAMPLE_DT over [0, T_END] (a truth sampled otherwise was
    compared sample by sample with the run, up to the shorter of the two). Raises ValueError."""
    path = truth_path(truth_dir, label)
    try:
        with h5py.File(path, "r") as f:
            t, w = f["time"][:], f["constraints/displacement"][:]
    except (OSError, KeyError) as e:
        raise ValueError(f"cannot read the truth {path}: {e}; make it with `study_accuracy.py -o DIR` "
                         f"and give DIR/runs") from None
    want = np.arange(round(T_END / SAMPLE_DT) + 1) * SAMPLE_DT
    if t.shape != want.shape or not np.allclose(t, want, rtol=0, atol=1e-9) or w.reshape(t.size, -1).shape[1] != label:
        raise ValueError(f"{path} is not the truth of {SCENES[label]}: it holds {w.reshape(t.size, -1).shape[1]} "
                         f"constraint(s) sampled at {t.size} times up to {t[-1] if t.size else 0:g} s, not {label} "
                         f"every {SAMPLE_DT:g} s over [0, {T_END:g}] s")
    return w


def case(label: int, modes: int, rtol: float, enrichment: str, truth_dir: str, work: str) -> dict:
    w_truth = read_truth(truth_dir, label)
    scene = load_scene(os.path.join(ROOT, "jobs", SCENES[label]),
                       ["basis.cache=off", f"basis.modes={modes}", f"basis.enrichment={enrichment}",
                        f"integrator.rtol={rtol}", "integrator.t_end=0.2", "output.sample_dt=1e-4",
                        "output.snapshots=0", "basis.estimate_window=0.2"])
    path = os.path.join(work, f"case-{label}-{modes}-{rtol:g}-{enrichment}.h5")
    summary = run(scene, path, progress=False)
    with h5py.File(path, "r") as f:
        w = f["constraints/displacement"][:]
    if w.shape != w_truth.shape:
        raise ValueError(f"the run of {SCENES[label]} gave {w.shape[0]} samples, its truth {w_truth.shape[0]}")
    true = relative_difference(w, w_truth)
    walls = summary["timings"]
    return {"constraints": label, "modes": modes, "enrichment": enrichment, "rtol": rtol,
            "estimate": summary["estimated_error"], "true": true,
            "ratio": summary["estimated_error"] / true if true > 0 else float("nan"),
            "run_seconds": walls["basis"] + walls["integration"],
            "estimate_seconds": walls.get("estimate_basis", 0.0) + walls.get("estimate", 0.0)}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("truth_dir", metavar="TRUTH_DIR",
                        help="the folder of the truths: DIR/runs after `study_accuracy.py -o DIR` "
                             "(truth-<stops>-400-2.5e-06-0.2.h5)")
    parser.add_argument("-o", "--output", default="estimate.csv", metavar="OUT.csv",
                        help="the table of cases (default estimate.csv)")
    parser.add_argument("--modes", default="4,6,10,20,40", help="comma-separated mode counts (default 4,6,10,20,40)")
    parser.add_argument("--rtol", default="1e-6,1e-4", help="comma-separated rtols (default 1e-6,1e-4)")
    parser.add_argument("--enrichment", default="dbf,none",
                        help="comma-separated enrichments: dbf, static, none (default dbf,none)")
    args = parser.parse_args(argv)
    try:
        modes_list = [int(m) for m in args.modes.split(",")]
        rtols = [float(r) for r in args.rtol.split(",")]
    except ValueError:
        modes_list = rtols = []
    if not modes_list or min(modes_list) < 1 or not rtols or not all(0 < r < 1 for r in rtols):
        parser.error(f"--modes {args.modes!r} --rtol {args.rtol!r}: give whole numbers >= 1 and tolerances in (0, 1)")
    enrichments = args.enrichment.split(",")
    if not set(enrichments) <= {"dbf", "static", "none"}:
        parser.error(f"--enrichment {args.enrichment!r}: choose from dbf, static, none")
    for label in SCENES:   # every truth checked before the first case runs
        try:
            read_truth(args.truth_dir, label)
        except ValueError as e:
            parser.error(str(e))
    rows = []
    with tempfile.TemporaryDirectory() as work:
        for label in SCENES:
            for enrichment in enrichments:
                for modes in modes_list:
                    for rtol in rtols:
                        try:
                            row = case(label, modes, rtol, enrichment, args.truth_dir, work)
                        except (DbfError, ValueError) as e:
                            parser.exit(1, f"{parser.prog}: error: {SCENES[label]}, {modes} modes, rtol {rtol:g}, "
                                           f"{enrichment}: {str(e).splitlines()[0]}\n")
                        rows.append(row)
                        print(" ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in row.items()),
                              flush=True)
    with open(args.output, "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    ratio = np.array([r["ratio"] for r in rows])
    big = np.array([r["true"] > 0.01 for r in rows])
    print(f"{np.mean((ratio >= 0.5) & (ratio <= 2)):.0%} of {ratio.size} within 2x; "
          f"optimistic by more than 2x where true > 1 %: {int(np.sum(big & (ratio < 0.5)))}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
