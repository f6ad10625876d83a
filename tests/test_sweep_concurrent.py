"""Two sweeps on one ``--out`` at the same time keep every row (issue 22.2): the second
sweep's final rewrite of results.csv used to replace the file the first still appended
to (a 24-cell and a 2-cell sweep: 4 of the 24 rows kept, both exit 0)."""

from __future__ import annotations

import multiprocessing
import os

from vislam.core.simulate import SimulationOptions, simulate_drive
from vislam.tools.dataset_io import save_sequence
from vislam.tools.sweep import RESULTS_FILE, load_spec, read_results, run_sweep


def _spec(directory, name: str, seeds: list[int]):
    path = directory / f"{name}.yaml"
    path.write_text(f"datasets:\n  - path: drive.npz\nmodes: [localization]\noptions:\n  {name}: {{}}\n"
                    f"noise:\n  imu: {{velocity_noise_mps: 0.1}}\nseeds: {seeds}\n", encoding="utf-8")
    return load_spec(path)


def test_a_sweep_finishing_inside_another_keeps_every_row(tmp_path):
    save_sequence(simulate_drive(SimulationOptions(n_frames=10, seed=0)).sequence, tmp_path / "drive.npz")
    long, short = _spec(tmp_path, "long", list(range(6))), _spec(tmp_path, "short", [0, 1])
    out = tmp_path / "out"
    inner = []

    def on_row(row, done, total):  # the short sweep starts and finishes while the long one runs
        if done == 2:
            inner.append(run_sweep(short, out, figure=False))

    result = run_sweep(long, out, on_row=on_row, figure=False)
    assert len(inner) == 1 and inner[0].n_run == 2
    rows = read_results(out / RESULTS_FILE)
    assert sorted(r["options"] for r in rows) == ["long"] * 6 + ["short"] * 2
    assert len(result.rows) == 6 and all(r["status"] == "ok" for r in rows)


def _sweep_in_child(spec_path, out, ready, go):
    spec = load_spec(spec_path)
    ready.set()
    go.wait()
    run_sweep(spec, out, figure=False)


def test_concurrent_processes_keep_every_row(tmp_path):
    save_sequence(simulate_drive(SimulationOptions(n_frames=10, seed=0)).sequence, tmp_path / "drive.npz")
    specs = [_spec(tmp_path, f"set{i}", list(range(3))) for i in range(2)]
    out = tmp_path / "out"
    ctx = multiprocessing.get_context("fork" if hasattr(os, "fork") else "spawn")
    go = ctx.Event()
    procs, readies = [], []
    for spec in specs:
        ready = ctx.Event()
        p = ctx.Process(target=_sweep_in_child, args=(spec.source, out, ready, go))
        p.start()
        procs.append(p)
        readies.append(ready)
    for ready in readies:
        assert ready.wait(60)
    go.set()
    for p in procs:
        p.join(120)
        assert p.exitcode == 0
    rows = read_results(out / RESULTS_FILE)
    assert sorted(r["options"] for r in rows) == ["set0"] * 3 + ["set1"] * 3
