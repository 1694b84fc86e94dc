"""The calibration beside other jobs (issue 28): rounds of one calibration run each
(render._calibration_run, as ``bdpt calibrate`` repeats it) on an idle machine, beside
one CPU-bound process and beside two; per load, the median unit costs and their ratios
to the camera-walk ray's, which are what the decision compares.

    python benchmarks/experiments/calibration_load.py 6
"""
import multiprocessing
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
import mitsuba as mi                                                   # noqa: E402
import numpy as np                                                     # noqa: E402

NAMES = ["camera", "light", "stored", "connection", "path", "grid", "merge"]
LOADS = {"idle": 0, "one busy loop": 1, "two busy loops": 2}


def _busy() -> None:
    while True:
        pass


def main() -> None:
    rounds = int(sys.argv[1]) if len(sys.argv) > 1 else 6
    mi.set_variant("llvm_ad_rgb")
    import bdpt_drjit                                                  # noqa: F401
    render = sys.modules["bdpt_drjit.render"]      # (bdpt_drjit.render: the function)
    res = render._calibration_res()
    scenes = []
    for width, height in ((res, res), (res, res // 2)):
        box = mi.cornell_box()
        box["sensor"]["film"].update(width=width, height=height)
        scenes.append(mi.load_dict(box))
    render._calibration_run(*scenes, 0)                                 # kernels
    rows = {name: [] for name in LOADS}
    for i in range(rounds):
        for name, jobs in LOADS.items():
            busy = [multiprocessing.Process(target=_busy, daemon=True) for _ in range(jobs)]
            for p in busy:
                p.start()
            time.sleep(0.2)
            rows[name].append(render._calibration_run(*scenes, 1 + i))
            for p in busy:
                p.terminate()
    for name, runs in rows.items():
        units = np.median(np.array(runs), axis=0)
        print("%-15s %s" % (name, " ".join("%s=%.3g" % kv for kv in zip(NAMES, units))))
        ratios = np.median(np.array(runs) / np.array(runs)[:, :1], axis=0)
        print("%-15s / camera: %s" % ("", " ".join("%s=%.2f" % kv for kv in zip(NAMES, ratios))))


if __name__ == "__main__":
    main()
