"""The statistics behind vislam.core.results.JOB_LIMITS on the shared files (issue 22.7):
per file and mode, the share of tested observations gated, of landmarks rejected, the
longest stretch without a used observation and the largest frame interval. Defaults on
the sparse files, --velocity-noise 0.5 --angular-noise 0.05 on the dense ones.

    python benchmarks/run_warning_limits.py slam mapping smoother      # one JSON line per file and mode
"""
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))
from vislam.tools.dataset_io import load_sequence
from vislam.core.estimators import run
from vislam.core.options import FilterOptions
D = str(Path(__file__).resolve().parents[2] / "shared" / "data")
rows = []
for f in ["sparse/0020", "sparse/0027", "sparse/0042", "dense/0022", "dense/0027", "dense/0034"]:
    seq = load_sequence(f"{D}/{f}.npz")
    opts = FilterOptions(velocity_noise_mps=0.5, angular_noise_radps=0.05) if f.startswith("dense") else FilterOptions()
    t = seq.timestamps_s
    for mode in sys.argv[1:]:
        r = run(seq, mode, opts)
        s = r.stats
        used = r.frame_stats["used"]
        # longest run of frames without a used observation (after frame 0)
        best = (0, 0)
        k = 1
        while k < len(used):
            if used[k] == 0:
                j = k
                while j < len(used) and used[j] == 0:
                    j += 1
                dur = t[j - 1] - t[k - 1]
                if dur > best[0]:
                    best = (dur, j - k)
                k = j
            else:
                k += 1
        tested = s.observations_used + s.observations_gated
        lm = r.landmarks
        rej = int(np.count_nonzero(lm.rejected)) / max(len(lm), 1) if lm is not None else None
        row = dict(file=f, mode=mode, used=s.observations_used, gated_share=s.observations_gated / max(tested, 1),
                   rejected_share=rej, init=s.landmarks_initialized, longest_no_update_s=best[0],
                   longest_no_update_frames=best[1], max_dt=float(np.diff(t).max()), median_dt=float(np.median(np.diff(t))),
                   total=s.observations_total, partial=r.partial)
        print(json.dumps(row), flush=True)
