"""Repeat decisions of the shared files, float against rounded to integer pixels (issue 22.3).

For each file: the observations bit-identical to their track's previous frame (float and
rounded), the repeats vislam counts (``Sequence.repeated_mask``; the online detector of
the filters, ``FrameRepeats``; the stall buffer of SLAM's remap), whether the rounded
file's decisions equal the float file's, and the evidence found in the rounded file.

    python benchmarks/quantized_repeats.py [--data ../shared/data]
"""

from __future__ import annotations

import argparse
import json
import sys
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "src"))

from vislam.core.stalls import repeat_decisions, rounded_pixels  # noqa: E402
from vislam.tools.dataset_io import load_sequence  # noqa: E402

FILES = ["sparse/0020", "sparse/0027", "sparse/0042", "dense/0022", "dense/0027", "dense/0034"]


def bit_equal(obs) -> np.ndarray:
    prev = obs.previous_index()
    c = prev >= 0
    out = np.zeros(obs.n_observations, dtype=bool)
    out[c] = np.all(obs.pixels[c] == obs.pixels[prev[c]], axis=1)
    return out


def main() -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument("--data", default=str(ROOT.parent / "shared" / "data"))
    args = parser.parse_args()
    warnings.simplefilter("ignore", RuntimeWarning)
    ok = True
    for name in FILES:
        seq = load_sequence(Path(args.data) / f"{name}.npz")
        obs = seq.observations
        q = rounded_pixels(seq)
        (mf, of, bf), (mq, oq, bq) = repeat_decisions(seq), repeat_decisions(q)
        _, evidence = q.observations.repeat_evidence(q.repeat_motion())
        same = bool(np.array_equal(mq, mf) and np.array_equal(oq, mf) and bq == bf and np.array_equal(of, mf))
        ok &= same
        print(json.dumps({"file": name, "bit_identical_float": int(bit_equal(obs).sum()),
                          "bit_identical_rounded": int(bit_equal(q.observations).sum()), "repeats_float": int(mf.sum()),
                          "repeats_rounded": int(mq.sum()), "float_equals_bit_identity": bool(np.array_equal(mf, bit_equal(obs))),
                          "rounded_decisions_equal_float": same, "rounded_evidence": evidence}))
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
