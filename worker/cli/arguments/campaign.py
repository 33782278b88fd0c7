"""``osdar-ar campaign``: a dataset campaign (many variants from one spec)."""

from __future__ import annotations

import argparse
import os
from pathlib import Path


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "campaign",
        help="a dataset campaign: many augmented sequences from one spec",
        description="Dataset campaigns (the spec: worker/campaign/spec.py, examples/).",
    )
    csub = p.add_subparsers(dest="campaign_command", required=True)
    r = csub.add_parser(
        "run",
        help="run a campaign here (embedded, no server)",
        description="Validate SPEC (YAML or JSON), prepare each sequence once (the "
        "prepared cache), expand it into variants and make each as an augmentation job: "
        "OUT/archives/*.tar.gz, OUT/manifest.json + manifest.csv (variant, sequence, "
        "objects, gauge flags, AR quality) and OUT/contact_sheet.png. A re-run in the same "
        "OUT skips the variants already complete. Relative sequence paths are from the "
        "current directory.",
    )
    r.add_argument("spec", type=Path, help="campaign spec (.yaml, .yml or .json)")
    r.add_argument(
        "--out",
        type=Path,
        default=None,
        help="output folder (default: campaigns/<the spec's name>)",
    )
    r.add_argument(
        "--dry-run",
        action="store_true",
        help="expand and print the variants with their resolved positions "
        "(written to OUT/variants.json); run nothing",
    )
    r.add_argument(
        "--workers",
        type=int,
        default=min(2, os.cpu_count() or 1),
        help="processes for each variant's frames (default: min(2, CPUs))",
    )
    r.add_argument(
        "--cache-dir",
        type=Path,
        default=None,
        help="cache of prepared artifacts (default: prepared/ in the workers' cache, "
        "$OSDAR_AR_CACHE_DIR, itself default ./var/cache)",
    )
    _add_service_commands(csub)
    p.set_defaults(command_group="campaign")


def _service(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--url",
        default=os.environ.get("OSDAR_AR_URL", "http://127.0.0.1:8000"),
        help="the service (default: $OSDAR_AR_URL or http://127.0.0.1:8000)",
    )
    p.add_argument("--key", default=None, help="API key (default: $OSDAR_AR_API_KEY)")


def _add_service_commands(csub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    s = csub.add_parser(
        "submit",
        help="submit a campaign to a running service",
        description="Check SPEC, resolve its sequence paths to the key's sequence ids "
        "(registered, or uploaded when the service cannot read the folder) and POST it to "
        "/v1/campaigns (idempotent: the same resolved spec is the same campaign). Prints "
        "the campaign id.",
    )
    s.add_argument("spec", type=Path, help="campaign spec (.yaml, .yml or .json)")
    _service(s)
    s.add_argument(
        "--dry-run",
        action="store_true",
        help="expand only: print the variants with their resolved positions",
    )
    s.add_argument("--wait", action="store_true", help="follow the campaign to its end")
    s.add_argument("--idempotency-key", default=None, help="default: a digest of the resolved spec")
    d = csub.add_parser(
        "download",
        help="download a campaign's manifest and every variant's archive",
        description="OUT/manifest.json, OUT/manifest.csv and OUT/archives/*.tar.gz, with a "
        "progress bar; partial files are resumed (Range), complete ones skipped.",
    )
    d.add_argument("campaign_id", help="the campaign's id")
    _service(d)
    d.add_argument("--out", type=Path, default=None, help="output folder (default: campaigns/<id>)")
    d.add_argument("--wait", action="store_true", help="wait for the campaign to end first")
