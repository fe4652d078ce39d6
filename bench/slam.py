"""SLAM throughput at 640x480 on 2 threads, UWNet, XFeat and ORB, synchronous (mapping and loop closing inline) or
threaded.

    nice .venv/bin/python bench/slam.py [--frames 100] [--level clear] [--extractors uwnet_xfeat xfeat orb] [--stereo]
                                        [--no-loop]
    nice .venv/bin/python bench/slam.py --variant dev:turn9 --profile     # a robustness-matrix variant, per stage
    nice .venv/bin/python bench/slam.py --variant test:base --laps 16 --frames 2000 --extractors orb   # memory
    nice .venv/bin/python bench/slam.py --modes sync threaded threaded-gil   # the modes, one after the other
    nice .venv/bin/python bench/slam.py --ba-solvers gtsam schur  # the two bundle-adjustment solvers

Each extractor runs with its preset (`ruslam.slam.preset(name)`: the extractor options and SLAM settings that
`evaluate.py task=slam` uses, e.g. ORB at 1,000 keypoints, CLAHE conditioning, XFeat's and UWNet's LighterGlue
pair matcher); the bench only sets the mode, the BA solver, loop closing and the frame count on top.

For each extractor the baseline is feature extraction alone on the same (conditioned) frames, measured in this same
run; the SLAM figure is frames / wall time of the whole run (extraction, tracking, mapping and loop closing; in
threaded mode the mapper's thread runs alongside and the run ends when its queue is done), so the ratio says what
the SLAM adds on top of the extractor. Per-frame times are the tracking thread's (in threaded mode they exclude the
mapping it no longer waits for). Accuracy (APE after Sim3/SE3 alignment, % of path) is printed alongside, so a
faster setting that breaks tracking shows up. Goals (idle machine, 2 threads, synchronous, 100 frames): >= 10
frames/s with UWNet (a 10 Hz camera in real time), >= 15 with ORB at 1,000 keypoints.

Memory: the resident set size is sampled every 0.5 s during each SLAM run; the bench prints its peak and its
growth over the second half of the frames (MB per 1,000 frames) next to the map's final size, so a leak (growth
beyond what the map's points and keyframes hold) shows on a long run.

CPU: the process's CPU time (every thread, and the threaded mode's solver child) per frame is printed for the
extraction alone and for the SLAM run, with the frames/s that this many CPU-seconds allow on the machine's cores
if they were perfectly shared (`bound`): a goal above the bound cannot be met by scheduling alone, only by less work.

`--profile` runs the SLAM under cProfile and prints the time per stage (ms per frame, share of the run): each
stage is the cumulative time of the functions that implement it, so nested stages are listed under their own name
and counted in their parents too: in synchronous mode "track (all)" holds the keyframes' inline mapping and loop
closing ("tracking alone" is what remains), "pose optimisation" counts every pose-only optimisation (also the one
inside local map search), and the pair matcher (LighterGlue) is counted wherever it runs (tracking's fallbacks,
loop candidate checks). Load frame, condition, extract and track (all) add up to the whole run.
"""

from __future__ import annotations

import argparse
import cProfile
import dataclasses
import itertools
import logging
import os
import pstats
import resource
import threading
import time
from pathlib import Path

import numpy as np
import torch

from ruslam.data.readers import Trajectory
from ruslam.data.synthetic_sequence import synthetic_sequence
from ruslam.eval.trajectory import evaluate_trajectory
from ruslam.slam import SLAMConfig, preset, run
from ruslam.slam.bundle_adjustment import SOLVERS
from ruslam.slam.local_mapping import MappingConfig

# stage -> (file suffix, function) pairs whose cumulative times add up to it (see --profile)
STAGES = {
    "load frame": [("data/readers.py", "load")],
    "condition": [("slam/conditioning.py", "__call__")],
    "extract": [("slam/system.py", "make_frame")],
    "track (all)": [("slam/tracking.py", "track")],
    "  keyframe decision": [("slam/tracking.py", "_need_keyframe")],
    "  local map search": [("slam/tracking.py", "_track_local_map")],
    "  pose optimisation": [("slam/tracking.py", "_optimize")],
    "mapping (all)": [("slam/local_mapping.py", "process")],
    "  triangulate": [("slam/local_mapping.py", "_triangulate")],
    "  fuse": [("slam/local_mapping.py", "_fuse")],
    "  local BA": [("slam/local_mapping.py", "_local_ba_problem"), ("slam/local_mapping.py", "_solve"),
                   ("slam/local_mapping.py", "_write_back")],
    "    solver": [("slam/bundle_adjustment.py", "_schur_levenberg_marquardt"),
                   ("slam/bundle_adjustment.py", "_gtsam_levenberg_marquardt")],
    "  culling": [("slam/local_mapping.py", "_cull_points"), ("slam/local_mapping.py", "_cull_keyframes")],
    "loop closing (all)": [("slam/loop_closing.py", "process")],
    "  candidate checks": [("slam/loop_closing.py", "_verify")],
    "pair matcher (anywhere)": [("models/lightglue.py", "__call__")],
}


def stage_table(stats: pstats.Stats, frames: int, total: float, synchronous: bool) -> str:
    """Per-stage ms/frame and share of the total, from cumulative times of the stage's functions; in synchronous
    mode also tracking alone (track minus the mapping and loop closing it runs inline)."""
    cums = {stage: sum(v[3] for (path, _, name), v in stats.stats.items()
                       for suffix, fn in functions if name == fn and path.endswith(suffix))
            for stage, functions in STAGES.items()}
    if synchronous:
        cums["tracking alone"] = cums["track (all)"] - cums["mapping (all)"] - cums["loop closing (all)"]
    return "\n".join(f"  {stage:24s} {1e3 * cum / frames:8.1f} ms/frame {100 * cum / total:5.1f} %"
                     for stage, cum in cums.items())


class MemorySampler(threading.Thread):
    """Resident set size (MB) of this process and its children (the threaded mode's solver process) every `period`
    seconds, with the time of each sample."""

    def __init__(self, period: float = 0.5):
        super().__init__(daemon=True)
        self.period, self.samples, self.done = period, [], threading.Event()

    def run(self):
        page_mb = os.sysconf("SC_PAGE_SIZE") / 2**20
        while not self.done.is_set():
            self.samples.append((time.perf_counter(), sum(_rss_pages(pid) for pid in _self_and_children()) * page_mb))
            self.done.wait(self.period)

    def stop(self) -> np.ndarray:
        self.done.set()
        self.join()
        return np.array(self.samples)


def _self_and_children() -> list[str]:
    children = []
    for task in Path("/proc/self/task").iterdir():
        try:
            children += (task / "children").read_text().split()
        except OSError:  # a thread that just ended
            pass
    return ["self", *children]


def _rss_pages(pid: str) -> int:
    try:
        return int(Path(f"/proc/{pid}/statm").read_text().split()[1])
    except (OSError, IndexError):  # a child that just ended
        return 0


def memory_line(samples: np.ndarray, timings: np.ndarray) -> str:
    """Peak RSS and its growth over the second half of the frames (samples placed on frames by their time)."""
    if len(samples) < 4:
        return "memory: run too short to sample"
    frame_at = np.interp(samples[:, 0] - samples[0, 0], np.cumsum(timings), np.arange(1, len(timings) + 1))
    late = frame_at >= len(timings) / 2
    slope = np.polyfit(frame_at[late], samples[late, 1], 1)[0] if late.sum() >= 2 else float("nan")
    return f"peak RSS {samples[:, 1].max():.0f} MB, growth over the second half {1e3 * slope:.1f} MB / 1000 frames"


def cpu_seconds() -> float:
    """CPU time (user + system) of this process's threads and its finished children."""
    own, children = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


def cpu_line(label: str, cpu: float, frames: int) -> str:
    cores = os.cpu_count() or 1
    return f"{label} CPU {1e3 * cpu / frames:.0f} ms/frame (bound on {cores} cores: {cores * frames / cpu:.1f} fps)"


def load_sequence(args):
    """The embedded sequence, or `split:variant` of the robustness matrix (conf/dataset/robustness.yaml)."""
    if args.variant is None:
        return synthetic_sequence(args.level, stereo=args.stereo, num_frames=200, seed=0, progress=False)
    from omegaconf import OmegaConf  # noqa: PLC0415

    from ruslam.data.robustness import robustness_sequence  # noqa: PLC0415

    split, name = args.variant.split(":")
    grid = OmegaConf.load(Path(__file__).resolve().parents[1] / "conf" / "dataset" / "robustness.yaml")
    knobs = OmegaConf.to_container(grid.splits[split][name])
    if args.laps is not None:
        knobs["laps"] = args.laps
    return robustness_sequence(name, progress=False, **knobs)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--frames", type=int, default=100, help="first frames of the 200-frame sequence")
    parser.add_argument("--level", default="clear")
    parser.add_argument("--extractors", nargs="+", default=["uwnet_xfeat", "xfeat", "orb"],
                        help="extractor names, each with its preset (ruslam.slam.presets)")
    parser.add_argument("--stereo", action="store_true")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--no-loop", action="store_true", help="disable loop closing (APE with vs without)")
    parser.add_argument("--global-ba", action="store_true", help="full-map BA after a loop correction")
    parser.add_argument("--max-keypoints", type=int, default=None,
                        help="extractor keypoint cap (default: its preset's)")
    parser.add_argument("--variant", default=None, help="robustness-matrix variant split:name, e.g. dev:turn9")
    parser.add_argument("--laps", type=float, default=None, help="laps of the --variant (a long run for memory)")
    parser.add_argument("--profile", action="store_true", help="time per SLAM stage (cProfile)")
    parser.add_argument("--modes", nargs="+", default=["sync"], choices=["sync", "threaded", "threaded-gil"],
                        help="synchronous (inline mapping), threaded (mapping in its own thread, BA in a child "
                             "process) and/or threaded-gil (BA in the mapping thread: solver_process=false)")
    parser.add_argument("--mapping-backlog", type=int, default=SLAMConfig.mapping_backlog,
                        help="threaded: keyframes being mapped before the tracker waits (slam.mapping_backlog)")
    parser.add_argument("--ba-solvers", nargs="+", default=[MappingConfig.ba_solver], choices=list(SOLVERS),
                        help="mapping.ba_solver values to run (ruslam.slam.bundle_adjustment)")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    logging.basicConfig(level=logging.WARNING)
    seq = load_sequence(args)
    n = min(args.frames, len(seq))
    images = [seq.load(i) for i in range(n)]
    gt = Trajectory(seq.groundtruth.timestamps[:n], seq.groundtruth.poses[:n])
    print(f"sequence {seq.name}: {n} frames {seq.cameras[0].width}x{seq.cameras[0].height}, "
          f"{'stereo' if args.stereo else 'mono'}, path {gt.path_length():.2f} m, torch threads {args.threads}")
    print(f"{'extractor':22s} {'extract fps':>11s} {'SLAM fps':>9s} {'ratio':>6s} {'tracked':>8s} {'kfs':>4s} "
          f"{'loops':>5s} {'APE m':>7s} {'APE %path':>9s}")
    for name in args.extractors:
        extractor, preset_cfg = preset(name, **({} if args.max_keypoints is None else
                                                {"max_keypoints": args.max_keypoints}))
        conditioned = [[preset_cfg.conditioning(image) for image in frame] for frame in images]
        extractor.extract(conditioned[0][0])  # warm-up
        start, cpu = time.perf_counter(), cpu_seconds()
        for frame in conditioned:
            for image in frame:
                extractor.extract(image)
        extract_fps = n / (time.perf_counter() - start)
        extract_cpu = cpu_seconds() - cpu
        for mode, solver in itertools.product(args.modes, args.ba_solvers):
            # cProfile sees the main thread only: --profile makes each frame there (no prefetch thread)
            cfg = dataclasses.replace(
                preset_cfg, progress=False, synchronous=mode == "sync", solver_process=mode == "threaded",
                prefetch=not args.profile, mapping_backlog=args.mapping_backlog, max_frames=n,
                mapping=dataclasses.replace(preset_cfg.mapping, ba_solver=solver),
                loop=dataclasses.replace(preset_cfg.loop, enabled=not args.no_loop,
                                         global_bundle_adjustment=args.global_ba))
            profiler = cProfile.Profile() if args.profile else None
            if profiler:
                profiler.enable()
            sampler = MemorySampler()
            sampler.start()
            start, cpu = time.perf_counter(), cpu_seconds()
            result = run(seq, extractor, cfg)
            wall = time.perf_counter() - start
            slam_cpu = cpu_seconds() - cpu
            memory = sampler.stop()
            if profiler:
                profiler.disable()
            slam_fps = n / wall
            ape = float("nan")
            if len(result) >= 3:
                errors = evaluate_trajectory(Trajectory(result.timestamps, result.poses), gt,
                                             "se3" if args.stereo else "sim3")
                ape = errors.ape_rmse
            label = "/".join([name] + [mode] * (len(args.modes) > 1) + [solver] * (len(args.ba_solvers) > 1))
            print(f"{label:22s} {extract_fps:11.1f} {slam_fps:9.1f} {slam_fps / extract_fps:6.2f} "
                  f"{result.tracked_ratio:8.1%} {result.num_keyframes:4d} {len(result.loops):5d} {ape:7.4f} "
                  f"{100 * ape / gt.path_length():9.2f}")
            per_frame = np.sort(result.timings)
            print(f"{'':22s} per-frame ms: median {1e3 * np.median(per_frame):.0f}, p90 "
                  f"{1e3 * per_frame[int(0.9 * (n - 1))]:.0f}, max {1e3 * per_frame[-1]:.0f}")
            print(f"{'':22s} {memory_line(memory, result.timings)}; final map {result.num_keyframes} keyframes, "
                  f"{result.num_points} points")
            print(f"{'':22s} {cpu_line('extraction', extract_cpu, n)}; {cpu_line('SLAM', slam_cpu, n)}")
            if profiler:
                print(stage_table(pstats.Stats(profiler), n, wall, mode == "sync"))


if __name__ == "__main__":
    main()
