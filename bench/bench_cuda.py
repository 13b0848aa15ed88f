"""Benchmark: every learned method at batch 1 on a CUDA GPU (issue #28), beside IPM in the same run.

Each row is ``Mapper.map`` in full (the images copied to the GPU, resize, network, sigmoid, the
grid copied back) with ``MapperConfig(device="cuda", backend="torch")``, on the frames of one
synthetic drive of the method's rig, best and median of ``--repeat`` passes after a warm-up
(synchronized before the clock is read). ``--weights-dir DIR`` also times the weights files
found there (``<method>_<rig>_<input>.safetensors``, as shipped). The surround6 row at 20 Hz says
whether six cameras at 20 Hz fit (the node maps every synchronized set; the DDS side is not run
here: the GPU machine has no ROS). onnxruntime's CUDA provider is tried where installed; the
line says so where it is not.

    python bench/bench_cuda.py [--frames 20] [--repeat 3] [--weights-dir DIR] [--json FILE]
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:  # run from anywhere (the device runs it from its copy)
    sys.path.insert(0, str(REPO))

#: (row name, rig, MapperConfig overrides, input: labels | rgb)
ROWS = [
    ("IPM (occlusion on)", "surround6", dict(method="ipm"), "labels"),
    ("segipm", "surround6", dict(method="segipm", input_kind="rgb"), "rgb"),
    ("Bi-Mapper (labels)", "surround6", dict(method="bimapper"), "labels"),
    ("Bi-Mapper (rgb, chained)", "surround6", dict(method="bimapper", input_kind="rgb"), "rgb"),
    ("S2G2 (rgb)", "front1", dict(method="s2g2", input_kind="rgb", grid="ahead"), "rgb"),
    ("FocusBEV (rgb)", "front1", dict(method="focusbev", input_kind="rgb", grid="ahead"), "rgb"),
]


def frames_of(rig_name: str, grid, n: int, kind: str) -> list[dict]:
    """``n`` frames of a synthetic drive of ``rig_name``: per camera its label or RGB image."""
    from bev_mapper_core.geometry.rig import preset_rig
    from bev_mapper_core.synth import SynthConfig, generate_drive

    drive = generate_drive(preset_rig(rig_name), grid, SynthConfig(frames=n, seed=7))
    return [{c: (cam.rgb if kind == "rgb" else cam.labels) for c, cam in f.cameras.items()} for f in drive]


def time_mapper(mapper, frames: list[dict], repeat: int) -> tuple[float, float]:
    """Best and median ms/frame of ``mapper.map`` over ``frames`` (``repeat`` passes, synchronized)."""
    import torch

    sync = torch.cuda.synchronize if torch.cuda.is_available() else (lambda: None)
    mapper.map(frames[0])
    sync()
    runs = []
    for _ in range(repeat):
        t = time.perf_counter()
        for f in frames:
            mapper.map(f)
        sync()
        runs.append((time.perf_counter() - t) * 1000.0 / len(frames))
    return min(runs), statistics.median(runs)


def onnxruntime_cuda() -> str:
    """Whether onnxruntime's CUDA provider is there (the line for the table)."""
    try:
        import onnxruntime as ort
    except ImportError:
        return "onnxruntime not installed"
    providers = ort.get_available_providers()
    if "CUDAExecutionProvider" in providers:
        return f"onnxruntime {ort.__version__}: CUDAExecutionProvider available"
    return f"onnxruntime {ort.__version__}: no CUDA provider ({', '.join(providers)}); not measured"


def main(argv=None) -> int:
    """Command line entry (see the module docstring)."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--weights-dir", default=None, help="also time the weights files found here")
    ap.add_argument("--json", default=None)
    ap.add_argument("--device", default="cuda", help="cuda (the point); cpu checks the script")
    a = ap.parse_args(argv)

    import torch

    if a.device == "cuda" and not torch.cuda.is_available():
        print("error: no CUDA device", file=sys.stderr)
        return 1
    from bev_mapper_core.geometry.grid import grid_preset
    from bev_mapper_core.geometry.rig import preset_rig
    from bev_mapper_core.mapper import MapperConfig, create_mapper

    rows = list(ROWS)
    if a.weights_dir:
        for path in sorted(Path(a.weights_dir).glob("*.safetensors")):
            method, rig, kind = path.stem.split("_")[:3]
            over = dict(method=method, input_kind=kind, weights=str(path))
            if rig == "front1":
                over["grid"] = "ahead"
            rows.append((f"{method} ({kind}, {path.name})", rig, over, kind))
    dev_name = torch.cuda.get_device_name() if a.device == "cuda" else platform.processor() or "cpu"
    print(f"{dev_name}, torch {torch.__version__}, {platform.machine()}; batch 1, "
          f"{a.frames} frames x {a.repeat} passes")
    print(onnxruntime_cuda())
    out, frames = [], {}
    for name, rig_name, over, kind in rows:
        over = dict(over)
        grid = grid_preset(over.pop("grid", "surround"))
        rig = preset_rig(rig_name)
        try:
            mapper = create_mapper(rig, grid, MapperConfig(device=a.device, backend="torch", **over))
            key = (rig_name, kind, grid.shape)
            if key not in frames:
                frames[key] = frames_of(rig_name, grid, a.frames, kind)
            best, med = time_mapper(mapper, frames[key], a.repeat)
        except Exception as exc:  # noqa: BLE001 - one row failing leaves the others
            print(f"{name:40s} failed: {type(exc).__name__}: {exc}")
            out.append({"row": name, "error": str(exc)})
            continue
        row = {"row": name, "rig": rig_name, "ms_best": round(best, 2), "ms_median": round(med, 2),
               "fps": round(1000.0 / best, 1)}
        fit = ""
        if rig_name == "surround6":  # a synchronized set every 50 ms
            fit = f" (6 cameras at 20 Hz: {'fits' if best < 50.0 else 'does not fit'})"
        print(f"{name:40s} {best:7.2f} ms/frame (median {med:.2f}) = {1000.0 / best:7.1f} FPS{fit}")
        out.append(row)
    if a.json:
        Path(a.json).write_text(json.dumps({"device": dev_name, "torch": torch.__version__,
                                            "onnxruntime": onnxruntime_cuda(), "rows": out}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
