"""Markdown reports of the bench, generated from its JSON and stamped with what measured it.

``osdar-ar bench [--hard] --json FILE --markdown REPORT.md`` writes the report of the run;
``osdar-ar bench --report FILE.json --markdown REPORT.md`` writes it again from a saved
JSON (the stamp is the one recorded when the figures were measured). A report keeps the
hand-written text above its :data:`FIGURES_HEADING` and replaces everything below it, so
the prose around the figures survives a re-run and the figures are never typed by hand.
"""

from __future__ import annotations

import datetime
import importlib.metadata
import os
import subprocess
from pathlib import Path
from typing import Any

from worker.bench.paper import PAPER_STRATEGY, PAPER_TABLE, format_table

#: Everything below this heading in a report is generated.
FIGURES_HEADING = "## Figures"
CAMERA_SHORT = {"rgb_center": "C1", "rgb_highres_center": "C2"}


def provenance() -> str:
    """ "osdar-ar <version>, commit <short hash>, <date>, <cores> cores." (the commit when
    run from a git checkout)."""
    try:
        version = importlib.metadata.version("osdar-ar")
    except importlib.metadata.PackageNotFoundError:
        version = "unknown"
    try:
        commit = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"],
            cwd=Path(__file__).resolve().parent,
            capture_output=True,
            text=True,
            timeout=10,
            check=True,
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"],
            cwd=Path(__file__).resolve().parent,
            capture_output=True,
            text=True,
            timeout=10,
            check=True,
        ).stdout.strip()
        if dirty:
            commit += " with uncommitted changes"
    except (OSError, subprocess.SubprocessError):
        commit = "unknown"
    today = datetime.date.today().isoformat()
    return f"osdar-ar {version}, commit {commit}, {today}, {os.cpu_count()} cores."


def with_figures(md: Path, figures: str, title: str) -> str:
    """The report's text: an existing report's text above :data:`FIGURES_HEADING` (else
    ``# title``), then the heading and ``figures``."""
    head = f"# {title}\n\n"
    if md.is_file() and FIGURES_HEADING in (old := md.read_text()):
        head = old[: old.index(FIGURES_HEADING)]
    return f"{head}{FIGURES_HEADING}\n\n{figures.rstrip()}\n"


def _num(x: Any, nd: int) -> str:
    return "-" if x is None else f"{x:.{nd}f}"


def paper_markdown(result: dict[str, Any]) -> str:
    """The figures of a paper-table run (``osdar-ar bench``): the table against the paper,
    the goal, preparation seconds, the speed-against-error front and the I/O floor."""
    s = result.get("settings", {})
    rows: list[dict[str, Any]] = result.get("rows", [])
    strategies = list(s.get("strategies") or dict.fromkeys(r["strategy"] for r in rows))
    out = [
        f"{'Quick run' if result.get('quick') else 'Full run'}: {s.get('frames')} frames, "
        f"lidar density {s.get('lidar_density')}, INS profile {s.get('ins_profile')}, seed "
        f"{s.get('seed')}, {result.get('seconds', 0.0):.0f} s. "
        f"{result.get('provenance', 'provenance not recorded.')}",
        "",
        "Paper RPE / jitter, mean ± std px at full resolution; [the paper's value] where the "
        "paper has the strategy (odometry = KISS-ICP, rails = rails-refined INS):",
        "",
        "```",
        format_table(rows, strategies),
        "```",
    ]
    g = result.get("goal") or {}
    if g:
        out += [
            "",
            f"Goal on {g['camera']}: best strategy `{g['best_strategy']}`, RPE "
            f"{g['best_rpe_mean']:.2f} px (goal <= {g['rpe_goal']}), jitter "
            f"{g['best_jitter_mean']:.2f} px (goal <= {g['jitter_goal']}): "
            f"**{'met' if g['met'] else 'MISS'}**.",
        ]
        if "ins_rpe_mean" in g:
            lo, hi = g["ins_paper_band"]
            inside = lo <= g["ins_rpe_mean"] <= hi
            out.append(
                f"Raw INS RPE {g['ins_rpe_mean']:.1f} px against the paper's band "
                f"{lo:.1f}-{hi:.1f} px: {'inside' if inside else '**outside**'}."
            )
    out += ["", "| strategy | preparation s (median over sequences) |", "|---|---|"]
    for st in strategies:
        sec = sorted(r["seconds"] for r in rows if r["strategy"] == st and r["seconds"])
        out.append(f"| {st} | {_num(sec[len(sec) // 2] if sec else None, 1)} |")
    front = {p["config"] for p in result.get("pareto", [])}
    if result.get("pareto_all"):
        out += [
            "",
            "Speed against error (first sequence, rgb_highres_center; * on the Pareto front):",
            "",
            "| config | seconds | RPE px | jitter px | front |",
            "|---|---|---|---|---|",
        ]
        for p in sorted(result["pareto_all"], key=lambda p: p["seconds"]):
            out.append(
                f"| {p['config']} | {p['seconds']:.1f} | {_num(p['error_px'], 2)} | "
                f"{_num(p.get('jitter_px'), 2)} | {'*' if p['config'] in front else ''} |"
            )
    fr = result.get("floor")
    if fr:
        out += [
            "",
            f"I/O floor ({fr['frames']} frames, {fr['workers']} worker(s)): job "
            f"{fr['job_s']:.2f} s, floor {fr['floor_s']:.2f} s, job / floor "
            f"{fr['floor_ratio']:.2f}.",
        ]
    return "\n".join(out)


def paper_gap_markdown(result: dict[str, Any]) -> str:
    """Our mean RPE over the paper's per (sequence, camera, strategy) (ratio < 1: better)."""
    lines = [
        "| seq | cam | strategy | ours px | paper px | ours / paper |",
        "|---|---|---|---|---|---|",
    ]
    for r in result.get("rows", []):
        paper = PAPER_TABLE.get((r["sequence"], r["camera"]), {})
        p = paper.get(PAPER_STRATEGY.get(r["strategy"], ""))
        if p is None or r["rpe_mean"] is None:
            continue
        lines.append(
            f"| {r['sequence'].split('_')[-1]} | {CAMERA_SHORT.get(r['camera'], r['camera'])} | "
            f"{r['strategy']} | {r['rpe_mean']:.1f} | {p[0]:.1f} | {r['rpe_mean'] / p[0]:.2f} |"
        )
    return "\n".join(lines)


def hard_markdown(result: dict[str, Any]) -> str:
    """The figures of a hard-case run (``osdar-ar bench --hard``): one row per case."""
    cases: list[dict[str, Any]] = result.get("hard_cases", [])
    n_ok = sum(bool(c["ok"]) for c in cases)
    out = [
        f"{'Reduced' if result.get('quick') else 'Full'} run: {n_ok} of {len(cases)} cases "
        f"within their bounds, {result.get('seconds', 0.0):.0f} s. "
        f"{result.get('provenance', 'provenance not recorded.')}",
        "",
        "| # | case | error | bound | unit | | warning given | what degrades |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for c in cases:
        err = "-" if c["error"] is None else f"{c['error']:.3g}"
        verdict = "ok" if c["ok"] else "**MISS**"
        warn = str(c.get("warning") or "-").replace("|", "/")
        degrades = str(c.get("degrades") or "-").replace("|", "/")
        out.append(
            f"| {c['case']} | {c['title']} | {err} | {c['bound']:g} | {c['unit']} | "
            f"{verdict} | {warn} | {degrades} |"
        )
    return "\n".join(out)


def bench_markdown(result: dict[str, Any]) -> tuple[str, str]:
    """(title, figures) of a bench result: the hard cases' or the paper table's."""
    if "hard_cases" in result:
        return "The hard cases", hard_markdown(result)
    figures = paper_markdown(result)
    gap = paper_gap_markdown(result)
    if gap.count("\n") > 1:
        figures += "\n\nOur RPE against the paper's, per row:\n\n" + gap
    return "The paper table", figures


def write_bench_markdown(result: dict[str, Any], md: Path) -> Path:
    """Write (or rewrite below its figures heading) the markdown report of a bench result."""
    title, figures = bench_markdown(result)
    md = Path(md)
    md.parent.mkdir(parents=True, exist_ok=True)
    md.write_text(with_figures(md, figures, title))
    return md
