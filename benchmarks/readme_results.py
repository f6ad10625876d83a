"""The results table of README.md and docs/benchmarks.md, regenerated from `vislam run`.

For each shared drive with ground truth (sparse 0020, sparse 0027, dense 0027) this runs

    python -m vislam run DATA --mode MODE --auto --gt GT --out TMPDIR --quiet

for localization, SLAM and (unless --no-smoother) the refined smoother (``--mode smoother
--refine``), reads each run's summary.json, and prints the table in Markdown: camera-frame
metrics (the estimate turned into left-camera poses with the calibration the filter
used, against the ground truth as it is). ``--auto`` runs ``vislam check`` first and
applies what it finds: on all three drives the corrected IMU-camera translation (the
files store imu_T_cam's), on the dense drive also the white IMU noise it measures (about
0.5 m/s and 0.05 rad/s) and a pitch-rate bias.

    python benchmarks/readme_results.py                      # print the table (about 3-5 min)
    python benchmarks/readme_results.py --write README.md docs/benchmarks.md   # replace it in place

``--write`` replaces the text between ``<!-- results:begin -->`` and ``<!-- results:end -->``
in each file. Run from the repository root with vislam installed; ``--data DIR`` for data
elsewhere than ../shared/data. tests/test_docs_examples.py checks one row of the table
against a fresh run (sparse 0027, SLAM).
"""

from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
DEFAULT_DATA = REPO.parent / "shared" / "data"
#: (row label, data file, ground truth, extra flags)
DRIVES = [
    ("sparse 0020 (clean IMU)", "sparse/0020.npz", "groundtruth/0020.txt", []),
    ("sparse 0027 (clean IMU)", "sparse/0027.npz", "groundtruth/0027.txt", []),
    ("dense 0027 (noisy IMU)", "dense/0027.npz", "groundtruth/0027.txt", []),
]
BEGIN, END = "<!-- results:begin -->", "<!-- results:end -->"
HEADER = ("| drive | localization ATE | SLAM ATE | SLAM KITTI t, r | landmarks (rejected) | refined smoother ATE, KITTI t |\n"
          "|---|---:|---:|---:|---:|---:|")


def run_summary(data: Path, gt: Path, mode: list[str], flags: list[str]) -> dict:
    """summary.json of one `vislam run` (raises on a failed run)."""
    with tempfile.TemporaryDirectory(prefix="vislam-readme-") as tmp:
        out = Path(tmp) / "run"
        cmd = [sys.executable, "-m", "vislam", "run", str(data), *mode, "--auto", "--gt", str(gt), "--out", str(out),
               "--quiet", *flags]
        subprocess.run(cmd, check=True)
        return json.loads((out / "summary.json").read_text(encoding="utf-8"))


def table_row(label: str, loc: dict, slam: dict, smoother: dict | None) -> str:
    ev = slam["evaluation"]
    cells = [label, f"{loc['evaluation']['cam_ape_rmse_m']:.2f} m", f"{ev['cam_ape_rmse_m']:.2f} m",
             f"{ev['cam_kitti_t_pct']:.2f} %, {ev['cam_kitti_r_deg_per_100m']:.2f} °/100 m",
             f"{slam['landmarks_in_map']} ({slam['landmarks_rejected']})"]
    if smoother is None:
        cells.append("not run")
    else:
        se = smoother["evaluation"]
        cells.append(f"{se['cam_ape_rmse_m']:.2f} m, {se['cam_kitti_t_pct']:.2f} %")
    return "| " + " | ".join(cells) + " |"


def parse_table(text: str) -> dict[str, list[str]]:
    """{drive label: [cells after the label]} of the results table in ``text``."""
    block = text.split(BEGIN, 1)[1].split(END, 1)[0]
    rows = {}
    for line in block.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) == 6 and not cells[0].startswith(("drive", "---")):
            rows[cells[0]] = cells[1:]
    return rows


def build_table(data: Path, smoother: bool) -> str:
    rows = []
    for label, rel, gt_rel, flags in DRIVES:
        data_file, gt = data / rel, data / gt_rel
        loc = run_summary(data_file, gt, ["--mode", "localization"], flags)
        slam = run_summary(data_file, gt, ["--mode", "slam"], flags)
        sm = run_summary(data_file, gt, ["--mode", "smoother", "--refine"], flags) if smoother else None
        rows.append(table_row(label, loc, slam, sm))
        print(rows[-1], file=sys.stderr, flush=True)
    return "\n".join([HEADER, *rows])


def write_into(path: Path, table: str) -> None:
    text = path.read_text(encoding="utf-8")
    if BEGIN not in text or END not in text:
        raise SystemExit(f"{path}: no {BEGIN} ... {END} block to replace")
    new = re.sub(re.escape(BEGIN) + r".*?" + re.escape(END), lambda _m: f"{BEGIN}\n{table}\n{END}", text,
                 count=1, flags=re.S)
    path.write_text(new, encoding="utf-8")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA, help="the shared data folder (../shared/data)")
    parser.add_argument("--no-smoother", action="store_true", help="leave out the refined smoother (faster)")
    parser.add_argument("--write", nargs="+", type=Path, metavar="FILE",
                        help="replace the table between the results markers in these files")
    args = parser.parse_args(argv)
    if not (args.data / "sparse" / "0027.npz").is_file():
        print(f"readme_results: no shared data in {args.data} (--data DIR)", file=sys.stderr)
        return 2
    table = build_table(args.data, smoother=not args.no_smoother)
    print(table)
    for path in args.write or ():
        write_into(path, table)
        print(f"wrote the table into {path}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
