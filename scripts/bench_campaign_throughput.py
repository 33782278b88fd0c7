# ruff: noqa: T201 (a script: prints its table)
"""Campaign throughput with 1 and with 2 worker processes, and a variant's time in a
campaign against the same variant run as a job of its own (issue 17, item 6).

Per worker count, in one run (scripts/service_bench.py): a fresh database (SQLite or a
PostgreSQL schema) and store, a Redis broker on a DB number of its own (flushed), a real
``celery worker --pool prefork --concurrency N`` subprocess, the API in-process. The
synthetic sequences are registered, a dry run of the campaign fills the preparation cache
(the expansion prepares each sequence once; every variant reuses it) and the worker
processes are warmed by a job each; then the campaign is submitted and timed from its POST
to its end (the manifest written). Variants per minute for each worker count, their
ratio (goal >= 1.8), the busy cores, the worker threads' wait for a CPU (Linux schedstat:
what the machine's other work took), the stage seconds per variant, the worker processes'
share of the time spent inside a stage (the rest: dispatch, waits between stages, idle
processes), and the load averages (the machine is shared). Over each campaign, the cores
each kind of process used (``CpuSplit``, sampled once a second from /proc: the worker
children, the celery parent, this process's polling thread and its in-process API, Redis,
and "other": the machine's busy time less those - other sessions' work), the worker
children's threads by name (on a CPU / runnable waiting for one), their main threads'
sleep, and the tasks' counts and seconds from the worker's log. With one worker process,
``--singles`` of the campaign's variants are then run again one at a time as jobs of their
own (the variant's job spec, POST /v1/jobs): the per-variant time, a job's first stage
to its published result, in the campaign (median over its variants) against as a single
job (median of the singles), and variant by variant (the goal's "for the same variant":
the obstacles' costs differ, so a few singles' median is not the campaign's), goal <= 1.1;
beside it the variants' own stage seconds, the campaign's wall time / variants against a
single job's POST to SUCCEEDED, and the worker's CPU seconds per variant.

Defaults: 2 synthetic sequences (fire_site, station) of 40 frames at 0.15 of the real
resolution, 4 built-in obstacles, 3 explicit track placements: 24 variants of 2 chunks.

    .venv/bin/python scripts/bench_campaign_throughput.py [--frames 40] [--db postgres]
        [--one-threads 0,1] [--pairs N]

``--one-threads 0,1``: the 1-process campaign once with the workers' own thread caps
(all cores) and once with 1 thread: whether one process should use the second core.

``--pairs N``: the 1- and the 2-process campaigns N times, in alternating order, and the
ratio of their median variants/min (the first pair is the one reported in full). The
machine's speed drifts between campaigns (a variant's CPU seconds 3.7-6.0 on one machine
in one day): one pair's ratio moved 1.73-2.02 over four runs of the same code.

``--profile DIR``: py-spy (if installed: it is no dependency of the project; 0.3.14 reads
this machine's Python 3.11.7, 0.4.3 does not find its version) samples the worker's process
tree during the 2-process campaign into DIR/workers.speedscope.json.
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from scripts.service_bench import (
    TERMINAL,
    CpuSplit,
    Service,
    load_averages,
    service,
    stage_line,
    stage_seconds,
)
from worker.synth.generator import SynthConfig, generate

REDIS_URL = "redis://127.0.0.1:6379/8"
SCENES = ("fire_site", "station")
OBSTACLES = ("person", "rock", "cow", "fallen_tree")
#: Explicit track placements (s m ahead of the first frame, offset m): within the track
#: that the short synthetic sequences prepare.
PLACEMENTS = ((8.0, 0.0), (10.0, 1.2), (12.0, -1.2))


def campaign_spec(seq_ids: list[str], obstacles: list[str], name: str) -> dict[str, Any]:
    """sequences x obstacles x placements explicit variants (24 by default)."""
    return {
        "name": name,
        "seed": 1,
        "sequences": [{"id": s} for s in seq_ids],
        "obstacles": [{"builtin": b} for b in obstacles],
        "placements": [
            {"explicit": {"mode": "track", "s": s, "offset": o, "yaw_deg": 90.0}}
            for s, o in PLACEMENTS
        ],
        "job": {"cameras": ["rgb_center", "rgb_highres_center"], "lidar": True, "strategy": "ins"},
    }


@dataclass
class Run:
    """One worker count's figures."""

    workers: int
    threads: int = 0  # per worker process (0: the workers' own caps, cores // processes)
    variants: int = 0
    wall_s: float = 0.0
    cores: float = 0.0
    runqueue_s: float = 0.0  # the workers' threads runnable, waiting for a CPU
    cpu_per_variant_s: float = 0.0  # the worker tree's seconds on a CPU / variants
    single_cpu_s: float = 0.0  # the same per single job
    load: str = ""
    stages: dict[str, float] = field(default_factory=dict)
    work_s: list[float] = field(default_factory=list)  # per variant: its stages' seconds
    elapsed_s: list[float] = field(default_factory=list)  # per variant: started -> finished
    single_wall_s: list[float] = field(default_factory=list)
    single_elapsed_s: list[float] = field(default_factory=list)
    single_work_s: list[float] = field(default_factory=list)
    paired_elapsed_s: list[float] = field(default_factory=list)  # the singles' variants, in it
    singles_load: str = ""
    split: str = ""  # cores by process kind over the campaign (CpuSplit)
    thread_split: str = ""  # the worker children's threads by name
    idle_parts: list[float] = field(default_factory=list)  # idle cores per tenth of it
    task_s: dict[str, tuple[int, float]] = field(default_factory=dict)  # from the worker log
    edges: str = ""  # each process's idle before its first and after its last task
    single_stages: dict[str, float] = field(default_factory=dict)

    @property
    def threads_label(self) -> str:
        n = self.threads or max(1, (os.cpu_count() or 1) // self.workers)
        return f"{n} thread(s) each{'' if self.threads else ' (the caps)'}"

    @property
    def per_min(self) -> float:
        return 60.0 * self.variants / self.wall_s

    @property
    def in_stages(self) -> float:
        """The worker processes' share of the campaign's wall time spent inside a stage
        (the variants' stage seconds over processes x wall): the rest is dispatch, the
        broker, waits between stages and idle processes."""
        return sum(self.work_s) / (self.workers * self.wall_s)


def _wait_campaign(
    svc: Service, campaign_id: str, states: tuple[str, ...], timeout_s: float
) -> dict[str, Any]:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        c = svc.get(f"/v1/campaigns/{campaign_id}", variants_limit=1)
        if c["state"] in states:
            return c
        time.sleep(0.5)
    raise RuntimeError(f"campaign {campaign_id} not {states} after {timeout_s} s")


def _variant_jobs(svc: Service, campaign_id: str) -> list[dict[str, Any]]:
    """The jobs of the campaign's variants, in the variants' order."""
    variants: list[dict[str, Any]] = []
    while True:
        page = svc.get(f"/v1/campaigns/{campaign_id}", variants_limit=100,
                       variants_offset=len(variants))  # fmt: skip
        variants += page["variants"]
        if len(variants) >= page["progress"]["variants"] or not page["variants"]:
            return [svc.job(v["job_id"]) for v in variants]


def _work_s(job: dict[str, Any]) -> float:
    return float(sum((job["timings"] or {}).values()))


def _elapsed_s(job: dict[str, Any]) -> float:
    """The job's own time: its first stage started to its result published."""
    started, finished = (datetime.fromisoformat(job[k]) for k in ("started_at", "finished_at"))
    return (finished - started).total_seconds()


def _profile(proc: Any, out: Path | None) -> subprocess.Popen[bytes] | None:
    spy = shutil.which("py-spy") or str(Path(sys.executable).with_name("py-spy"))
    if out is None or not Path(spy).exists():
        return None
    out.mkdir(parents=True, exist_ok=True)
    return subprocess.Popen([spy, "record", "--pid", str(proc.pid), "--subprocesses",
                             "--format", "speedscope", "--rate", "50", "--idle",
                             "--output", str(out / "workers.speedscope.json")],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)  # fmt: skip


def run_campaign(
    folders: list[Path],
    workers: int,
    root: Path,
    args: argparse.Namespace,
    *,
    threads: int = 0,
    singles: bool = False,
) -> Run:
    run = Run(workers, threads)
    with service(root / f"w{workers}_t{threads}", workers, redis_url=args.redis_url,
                 db=args.db, threads=threads) as svc:  # fmt: skip
        seq_ids = [svc.register(f) for f in folders]
        obstacles = list(args.obstacles.split(","))
        # warm: the preparation cache (a dry run expands), every worker process (a job each)
        dry = svc.post("/v1/campaigns?dry_run=true", campaign_spec(seq_ids, obstacles, "warm"))
        _wait_campaign(svc, dry["id"], ("EXPANDED", "FAILED"), 900)
        first = svc.get(f"/v1/campaigns/{dry['id']}", variants_limit=1)["variants"][0]
        warm_spec = {"sequence_id": first["sequence_id"], **_job_of(first)}
        svc.wait_jobs([svc.post("/v1/jobs", warm_spec)["id"] for _ in range(workers)], 900)

        spy = _profile(svc.proc, args.profile) if workers == 2 else None
        log = svc.proc_log
        log_at = log.stat().st_size if log.exists() else 0
        with CpuSplit(svc.proc) as split:
            cpu0, (on0, wait0), t0 = svc.cpu_s(), svc.sched_s(), time.perf_counter()
            c = svc.post("/v1/campaigns", campaign_spec(seq_ids, obstacles, f"bench_w{workers}"))
            end = _wait_campaign(svc, c["id"], tuple(s for s in (*TERMINAL, "PARTIAL")), 3600)
            run.wall_s = time.perf_counter() - t0
        run.split = split.line()
        run.idle_parts = split.idle_by_part(10)
        run.thread_split = ", ".join(f"{n} x{k} {on:.2f} on / {w:.2f} waiting"
                                     for n, k, on, w in split.threads()[:8])  # fmt: skip
        run.thread_split += "; main threads {:.2f} on / {:.2f} waiting / {:.2f} sleeping".format(
            *split.main_threads()
        )
        run.thread_split += f"; main + llvmpipe threads wanting a CPU {split.demand():.2f}"
        run.task_s = _task_seconds(log, log_at)
        run.edges = _process_edges(log, log_at)
        run.cores = (svc.cpu_s() - cpu0) / run.wall_s
        on1, wait1 = svc.sched_s()
        run.runqueue_s = wait1 - wait0
        run.load = load_averages()
        if spy is not None:  # py-spy writes its profile on SIGINT (not on SIGTERM)
            spy.send_signal(signal.SIGINT)
            spy.wait(120)
        if end["state"] != "SUCCEEDED":
            raise RuntimeError(f"campaign ended {end['state']}: {end['error']}")
        jobs = _variant_jobs(svc, c["id"])
        run.variants = len(jobs)
        run.cpu_per_variant_s = (on1 - on0) / len(jobs)
        run.work_s = [_work_s(j) for j in jobs]
        run.elapsed_s = [_elapsed_s(j) for j in jobs]
        run.stages = stage_seconds(svc, [j["id"] for j in jobs])
        if singles:
            _singles(svc, jobs, run, args.singles)
    return run


def _task_lines(log: Path, offset: int) -> list[tuple[str, str, float, float]]:
    """(process, task, start, end) of each task that succeeded in the worker log after
    ``offset`` (Celery's "[stamp: INFO/ForkPoolWorker-N] Task osdar_ar.<name>[<id>]
    succeeded in <s>s" lines; the start is the end stamp less the seconds)."""
    out = []
    with open(log, "rb") as f:
        f.seek(offset)
        for line in f.read().decode(errors="replace").splitlines():
            m = re.match(r"\[(\S+ \S+): \w+/([\w-]+)\] Task osdar_ar\.(\w+)\[[^]]*\] "
                         r"succeeded in ([0-9.]+)s", line)  # fmt: skip
            if m:
                end = datetime.strptime(m[1], "%Y-%m-%d %H:%M:%S,%f").timestamp()
                out.append((m[2], m[3], end - float(m[4]), end))
    return out


def _task_seconds(log: Path, offset: int) -> dict[str, tuple[int, float]]:
    """(count, seconds) of each task that succeeded in the worker log after ``offset``."""
    out: dict[str, tuple[int, float]] = {}
    for _, name, start, end in _task_lines(log, offset):
        n, sec = out.get(name, (0, 0.0))
        out[name] = (n + 1, sec + end - start)
    return out


def _process_edges(log: Path, offset: int) -> str:
    """Per worker process, from the worker log after ``offset`` (each task's end stamp
    less its seconds): how long it waited for its first task after the campaign's first
    one started, and how long it sat idle after its last task before the campaign's last
    one ended (the expansion at the start, the last variant's serial stages at the end)."""
    spans: dict[str, list[tuple[float, float]]] = {}
    for proc, _, start, end in _task_lines(log, offset):
        if proc.startswith("ForkPoolWorker"):
            spans.setdefault(proc, []).append((start, end))
    if not spans:
        return "no task lines"
    first = min(a for v in spans.values() for a, _ in v)
    last = max(b for v in spans.values() for _, b in v)
    return ", ".join(
        f"{w}: {min(a for a, _ in v) - first:.2f} s before its first task, "
        f"{last - max(b for _, b in v):.2f} s after its last"
        for w, v in sorted(spans.items())
    )


def _job_of(variant: dict[str, Any]) -> dict[str, Any]:
    """A dry-run variant's job fields (what its job spec would hold)."""
    objects = variant["objects"]
    if len(objects) == 1:
        one = objects[0]
        out = {"object": one["object"], "placement": one["placement"]}
    else:
        out = {"objects": [{"object": o["object"], "placement": o["placement"]} for o in objects]}
    return {"cameras": ["rgb_center", "rgb_highres_center"], "lidar": True, "strategy": "ins",
            **out}  # fmt: skip


def _singles(svc: Service, jobs: list[dict[str, Any]], run: Run, n: int) -> None:
    """``n`` of the campaign's variants, spread over it, each run alone as a job of its
    own with the variant's job spec (as a direct job may give it)."""
    picks = [jobs[round(i * (len(jobs) - 1) / max(1, n - 1))] for i in range(n)]
    ids = []
    on0 = svc.sched_s()[0]
    for job in picks:
        spec = {k: v for k, v in job["spec"].items() if k != "_test"}
        t0 = time.perf_counter()
        job_id = svc.post("/v1/jobs", spec)["id"]
        svc.wait_jobs([job_id], 900)
        run.single_wall_s.append(time.perf_counter() - t0)
        run.paired_elapsed_s.append(_elapsed_s(job))
        done = svc.job(job_id)
        run.single_work_s.append(_work_s(done))
        run.single_elapsed_s.append(_elapsed_s(done))
        ids.append(job_id)
    run.singles_load = load_averages()
    run.single_cpu_s = (svc.sched_s()[0] - on0) / n
    run.single_stages = stage_seconds(svc, ids)


def report(ones: list[Run], two: Run) -> None:
    for r in [*ones, two]:
        print(f"{r.workers} worker process(es), {r.threads_label}: {r.variants} variants in "
              f"{r.wall_s:.1f} s = "
              f"{r.per_min:.1f} variants/min, {r.cores:.2f} cores busy, "
              f"{r.runqueue_s / r.wall_s:.2f} threads waiting for a CPU ({r.load})")  # fmt: skip
        print(f"  stage seconds per variant: {stage_line(r.stages)}; the processes inside a "
              f"stage {100 * r.in_stages:.0f} % of the time")  # fmt: skip
        print(f"  cores over the campaign: {r.split}")
        tenths = " ".join(f"{x:.2f}" for x in r.idle_parts)
        print(f"  idle cores by tenth of the campaign: {tenths}")
        print(f"  the worker children's threads (cores): {r.thread_split}")
        print("  tasks (count, seconds): " + ", ".join(
            f"{k} {n} {sec:.1f}" for k, (n, sec) in sorted(r.task_s.items())))  # fmt: skip
        print(f"  the campaign's edges: {r.edges}")
    for one in ones:
        ratio = two.per_min / one.per_min
        print(f"throughput ratio 2 / 1 workers ({one.threads_label} in the 1): {ratio:.2f} "
              f"(goal >= 1.8: {'met' if ratio >= 1.8 else 'missed'})")  # fmt: skip
    one = ones[0]
    if not one.single_elapsed_s:
        print(f"  the worker's CPU seconds per variant: {one.cpu_per_variant_s:.2f} (1 worker), "
              f"{two.cpu_per_variant_s:.2f} (2 workers)")  # fmt: skip
        return
    elapsed, single = statistics.median(one.elapsed_s), statistics.median(one.single_elapsed_s)
    print(f"per-variant time, 1 worker: {elapsed:.2f} s in the campaign (median over its "
          f"variants, each job's first stage to its result) against {single:.2f} s as a single "
          f"job (median of {len(one.single_elapsed_s)}, {one.singles_load}): "
          f"{elapsed / single:.2f}x (goal <= 1.1: {'met' if elapsed / single <= 1.1 else 'missed'})"
          f"; 2 workers: {statistics.median(two.elapsed_s):.2f} s")  # fmt: skip
    pairs = [c / s for c, s in zip(one.paired_elapsed_s, one.single_elapsed_s, strict=True)]
    paired = statistics.median(pairs)
    print(f"  the same variants, campaign / single job: {paired:.2f}x (median of "
          f"{', '.join(f'{x:.2f}' for x in pairs)}; goal <= 1.1: "
          f"{'met' if paired <= 1.1 else 'missed'})")  # fmt: skip
    print(f"  single jobs' stage seconds: {stage_line(one.single_stages)}")
    work, single_work = statistics.median(one.work_s), statistics.median(one.single_work_s)
    print(f"  a variant's own stage seconds: {work:.2f} in the campaign, {single_work:.2f} as a "
          f"single job ({work / single_work:.2f}x); the campaign's wall / variants "
          f"{one.wall_s / one.variants:.2f} s against a single job's POST to SUCCEEDED "
          f"{statistics.median(one.single_wall_s):.2f} s")  # fmt: skip
    print(f"  the worker's CPU seconds per variant: {one.cpu_per_variant_s:.2f} in the campaign "
          f"(1 worker), {two.cpu_per_variant_s:.2f} (2 workers), {one.single_cpu_s:.2f} as a "
          "single job")  # fmt: skip


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=40, help="frames per synthetic sequence")
    ap.add_argument("--scale", type=float, default=0.15, help="image scale of the sequences")
    ap.add_argument("--obstacles", default=",".join(OBSTACLES),
                    help="built-ins (x 2 sequences x 3 placements = the variants)")  # fmt: skip
    ap.add_argument("--singles", type=int, default=3, help="variants re-run as single jobs")
    ap.add_argument("--redis-url", default=REDIS_URL, help="a Redis DB this run may flush")
    ap.add_argument("--db", choices=("sqlite", "postgres"), default="sqlite")
    ap.add_argument(
        "--threads", type=int, default=0,
        help="threads per process of the 2 workers (0: the workers' own caps)",
    )  # fmt: skip
    ap.add_argument(
        "--one-threads", default="0",
        help="threads of the 1 worker process, comma-separated: a 1-process campaign each "
        "(0: the workers' own caps, all cores); the singles run with the first",
    )  # fmt: skip
    ap.add_argument("--profile", type=Path, default=None, help="py-spy output folder")
    ap.add_argument(
        "--pairs", type=int, default=1,
        help="campaigns with 1 and with 2 processes, this many times in alternating order "
        "(1-2, 2-1, ...): the ratio of their median variants/min, steadier than one pair's "
        "on a machine whose speed drifts between campaigns",
    )  # fmt: skip
    args = ap.parse_args()

    root = Path(tempfile.mkdtemp(prefix="osdar_campaign_throughput_"))
    try:
        synth = {"frames": args.frames, "scale": args.scale, "lidar_density": 0.2}
        folders = [generate(root / s, SynthConfig(scene=s, **synth)).folder for s in SCENES]
        one_threads = [int(t) for t in args.one_threads.split(",")]
        ones = [run_campaign(folders, 1, root, args, threads=t, singles=i == 0 and args.singles > 0)
                for i, t in enumerate(one_threads)]  # fmt: skip
        two = run_campaign(folders, 2, root, args, threads=args.threads)
        more: list[tuple[Run, Run]] = []
        for k in range(1, max(1, args.pairs)):
            runs = {
                w: run_campaign(
                    folders, w, root, args, threads=args.threads if w == 2 else one_threads[0]
                )
                for w in ((2, 1) if k % 2 else (1, 2))
            }
            more.append((runs[1], runs[2]))
    finally:
        shutil.rmtree(root, ignore_errors=True)
    report(ones, two)
    if more:
        report_pairs([(ones[0], two), *more])
    return 0


def report_pairs(pairs: list[tuple[Run, Run]]) -> None:
    """Each pair's ratio and the ratio of the medians over the pairs (``--pairs``)."""
    for k, (one, two) in enumerate(pairs, 1):
        print(f"pair {k} ({'1 then 2' if k % 2 else '2 then 1'}): {one.per_min:.1f} and "
              f"{two.per_min:.1f} variants/min, ratio {two.per_min / one.per_min:.2f}; CPU s a "
              f"variant {one.cpu_per_variant_s:.2f} / {two.cpu_per_variant_s:.2f}, cores "
              f"{one.cores:.2f} / {two.cores:.2f}")  # fmt: skip
    m1 = statistics.median(one.per_min for one, _ in pairs)
    m2 = statistics.median(two.per_min for _, two in pairs)
    print(f"throughput ratio of the medians over {len(pairs)} pairs: {m2:.1f} / {m1:.1f} = "
          f"{m2 / m1:.2f} (goal >= 1.8: {'met' if m2 / m1 >= 1.8 else 'missed'})")  # fmt: skip


if __name__ == "__main__":
    sys.exit(main())
