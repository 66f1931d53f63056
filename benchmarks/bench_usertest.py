"""User-test benchmark: what a simulated study costs through the runner, the devices and the logs.

Run:  python benchmarks/bench_usertest.py [--participants N] [--emulator-participants N]

Prints, in one run, a baseline (the pure simulated study, :func:`masking_lab.usertest.design
.simulate_usertest`: no device, no log, no streaming) and, as ratios to it, per participant of
the paper's 120-trial user test:

- the full session on the in-process simulated device (streaming computed, logs fsynced);
- the full session through the firmware emulator over a real pseudo-terminal (every amplitude
  frame is a command and a reply on the pty), with the frames sent per trial and per second;

and the projected time of a 10-participant simulated study on each. Uses a rig with 20 dB more
gain than the shipped ground truth so that nothing is clipped. Takes about 20 s; timings depend
on the machine and its load, so compare ratios within one run.
"""

from __future__ import annotations

import argparse
import io
import statistics
import sys
import tempfile
import time
from pathlib import Path

import yaml

from masking_lab.formats.masking_params import write_masking_params
from masking_lab.formats.resources import shipped
from masking_lab.rendering.solver import MutualMasking
from masking_lab.simulation.observer import load_ground_truth, make_participant
from masking_lab.usertest.design import load_usertest
from masking_lab.usertest.observer import IdentificationObserver, simulate_usertest
from masking_lab.usertest.playback import render_objects
from masking_lab.usertest.runner import UserTestOptions, run_usertest

STIMULI = ("EV270", "MV120am40", "MV180", "MV270")


def setup(folder: Path) -> dict[str, Path]:
    gt = yaml.safe_load(shipped("protocols", "simulation/ground_truth.yaml").read_text("utf-8"))
    gt["unmasked_al_db_v"] = {k: v - 20.0 for k, v in gt["unmasked_al_db_v"].items()}
    (folder / "gt.yaml").write_text(yaml.safe_dump(gt), encoding="utf-8")
    rig = yaml.safe_load(shipped("protocols", "devices/default.yaml").read_text("utf-8"))
    for spec in rig["channels"].values():
        spec["max_level_db_sl"] = 65.0
    (folder / "rig.yaml").write_text(yaml.safe_dump(rig), encoding="utf-8")
    truth = load_ground_truth(folder / "gt.yaml")
    functions = []
    for fn in truth.masking:
        if "MV120" in (fn.target, fn.masker):  # the user test has no MV120 objects
            continue
        functions.append(
            {
                "target": fn.target,
                "masker": fn.masker,
                "masker_frequencies_hz": [120.0],
                "intercept_db": fn.intercept_db,
                "slope": fn.slope,
                "intercept_se_db": None,
                "slope_se": None,
                "intercept_ci_db": None,
                "slope_ci": None,
                "fitted_range_db_sl": [5.0, 25.0],
                "knee_db_sl": None,
                "adj_r2": None,
                "n_points": 5,
                "pooled_pairs": [f"{fn.target}|{fn.masker}"],
                "status": "fitted",
                "message": None,
            }
        )
    write_masking_params(
        folder / "params.json",
        {
            "schema_version": 1,
            "software_version": "bench",
            "created_utc": "1970-01-01T00:00:00Z",
            "provenance": {"source": "fit", "inputs": [], "settings": {}},
            "functions": functions,
        },
    )
    return {"gt": folder / "gt.yaml", "rig": folder / "rig.yaml", "params": folder / "params.json"}


def calibrate(data: Path, participant: str, gt: Path) -> None:
    import json

    person = make_participant(load_ground_truth(gt), participant, 0)
    path = data / participant / "calibration.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    als = {k: person.unmasked_al_db_v[k] for k in STIMULI}
    record = {"participant": participant, "unmasked_al_db_v": als, "sources": ["bench"]}
    path.write_text(json.dumps(record), encoding="utf-8")


def session(files: dict[str, Path], data: Path, participant: str, device: str, seed: int):
    calibrate(data, participant, files["gt"])
    options = UserTestOptions(
        shipped("protocols", "usertest.yaml"),
        participant,
        device=device,
        data_dir=data,
        params=files["params"],
        seed=seed,
        ground_truth=files["gt"],
        device_config=files["rig"],
        progress=False,
    )
    t0 = time.perf_counter()
    result = run_usertest(options, stream=io.StringIO())
    seconds = time.perf_counter() - t0
    if result.exit_code != 0:
        sys.exit(f"session failed: {result.message}")
    return seconds, result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--participants", type=int, default=3, help="sim-device sessions")
    parser.add_argument("--emulator-participants", type=int, default=2, help="emulator sessions")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        files = setup(folder)
        design = load_usertest(shipped("protocols", "usertest.yaml"))
        truth = load_ground_truth(files["gt"])
        pairs = {
            (mv, ev): MutualMasking.from_functions(
                truth.masking_function(mv, ev), truth.masking_function(ev, mv)
            )
            for mv, ev in design.stimulus_pairs()
        }
        objects = render_objects(design, pairs)
        observers = {f"P{i}": IdentificationObserver(pairs) for i in range(args.participants)}
        t0 = time.perf_counter()
        simulate_usertest(design, objects, observers, seed=1)
        base = (time.perf_counter() - t0) / args.participants

        sim = [
            session(files, folder / "sim", f"S{i:02d}", "sim", i)[0]
            for i in range(args.participants)
        ]
        emu, frames = [], []
        for i in range(args.emulator_participants):
            seconds, result = session(files, folder / "emu", f"E{i:02d}", "emulator", i)
            emu.append(seconds)
            from masking_lab.formats.session_log import read_log

            log = read_log(result.log_path)
            frames += [r["n_frames"] for r in log.records if r.get("record") == "usertest_trial"]
    sim_s, emu_s = statistics.median(sim), statistics.median(emu)
    per_trial = statistics.mean(frames)
    print("user test, 120 trials per participant (median over participants)")
    print(f"  baseline: pure simulation (no device, no log)  {base * 1000:8.1f} ms  1.0x")
    print(
        f"  session, simulated device                      {sim_s * 1000:8.1f} ms  "
        f"{sim_s / base:.1f}x"
    )
    print(
        f"  session, emulator over a pty                   {emu_s * 1000:8.1f} ms  "
        f"{emu_s / base:.1f}x   ({per_trial:.0f} frames per trial, "
        f"{per_trial * 120 / emu_s:.0f} frames/s)"
    )
    print("projected 10-participant simulated study, one process:")
    print(f"  simulated device {10 * sim_s:6.1f} s   emulator {10 * emu_s:6.1f} s")


if __name__ == "__main__":
    main()
