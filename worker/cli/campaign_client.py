"""``osdar-ar campaign submit`` and ``campaign download``: a campaign on a running service.

submit: the spec file is read and checked here (the same model as the service), each
sequence given by ``path`` is resolved to the key's sequence id (an already registered
sequence with that folder; else registered by path; else, when the service cannot read
that folder, uploaded as a tar), then POSTed to /v1/campaigns with an Idempotency-Key
derived from the resolved spec (a retried submit is the same campaign; ``--idempotency-key``
to choose one). ``--wait`` follows its progress to the end.

download: the manifest (JSON and CSV) and every finished variant's archive into
``OUT/archives/`` (the names of ``campaign run``), with a progress bar over the bytes. A
partial file (``*.partial``) is resumed with ``Range``; an archive already complete (its
size is the manifest's) is skipped. Redirects to presigned store URLs are followed (the
API key is not sent there).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import sys
import tarfile
import tempfile
import time
from pathlib import Path
from typing import Any

import httpx

from worker.campaign.run import CampaignRunError, load_campaign
from worker.cli.errors import CliError
from worker.cli.progress import progress_bar

TERMINAL = {"EXPANDED", "SUCCEEDED", "PARTIAL", "FAILED", "CANCELLED"}
CHUNK = 1 << 20


def _client(args: argparse.Namespace) -> httpx.Client:
    key = args.key or os.environ.get("OSDAR_AR_API_KEY")
    if not key:
        raise CliError("no API key: pass --key or set OSDAR_AR_API_KEY")
    return httpx.Client(
        base_url=args.url.rstrip("/"),
        headers={"Authorization": f"Bearer {key}"},
        timeout=httpx.Timeout(60.0, connect=10.0),
        follow_redirects=True,
    )


def _check(r: httpx.Response, what: str) -> dict[str, Any]:
    if r.status_code >= 400:
        try:
            detail = r.json().get("detail")
        except ValueError:
            detail = r.text[:500]
        if isinstance(detail, list):
            detail = "; ".join(
                f"{'.'.join(str(x) for x in d.get('loc', []))}: {d.get('msg')}" for d in detail
            )
        raise CliError(f"{what}: HTTP {r.status_code}: {detail}")
    body: dict[str, Any] = r.json()
    return body


# ---------------------------------------------------------------------------- submit
def _sequences_by_path(http: httpx.Client) -> dict[str, str]:
    out: dict[str, str] = {}
    offset = 0
    while True:
        page = _check(
            http.get("/v1/sequences", params={"limit": 100, "offset": offset}),
            "listing the key's sequences",
        )
        for s in page["items"]:
            if s.get("source") == "path":
                out[str(Path(s["path"]).resolve())] = s["id"]
        offset += len(page["items"])
        if not page["items"] or offset >= page["total"]:
            return out


def _upload(http: httpx.Client, folder: Path) -> str:
    with tempfile.TemporaryDirectory(prefix="osdar-ar-upload-") as tmp:
        tar = Path(tmp) / f"{folder.name}.tar"
        with tarfile.open(tar, "w") as t:
            t.add(folder, arcname=folder.name)
        with tar.open("rb") as f:
            r = http.post(
                "/v1/sequences/upload",
                params={"name": folder.name},
                content=f,
                headers={"Content-Type": "application/x-tar"},
            )
    return str(_check(r, f"uploading {folder}")["id"])


def resolve_sequences(http: httpx.Client, spec: dict[str, Any], base: Path) -> dict[str, Any]:
    """``spec`` with every ``path`` entry replaced by the key's sequence ``id`` (module
    docstring); placement filters naming a path name the id instead."""
    known: dict[str, str] | None = None
    renamed: dict[str, str] = {}
    entries = []
    for entry in spec["sequences"]:
        if entry.get("path") is None:
            entries.append(entry)
            continue
        folder = Path(entry["path"]).expanduser()
        folder = (folder if folder.is_absolute() else base / folder).resolve()
        if known is None:
            known = _sequences_by_path(http)
        seq_id = known.get(str(folder))
        if seq_id is None:
            r = http.post("/v1/sequences", json={"path": str(folder)})
            if r.status_code in (403, 404):  # the service cannot read it: upload
                if not folder.is_dir():
                    raise CliError(f"sequences: {entry['path']!r} is not a folder ({folder})")
                seq_id = _upload(http, folder)
            else:
                seq_id = str(_check(r, f"registering {folder}")["id"])
            known[str(folder)] = seq_id
        renamed[str(entry["path"])] = seq_id
        new = {k: v for k, v in entry.items() if k != "path"}
        new["id"] = seq_id
        new.setdefault("name", folder.name)
        entries.append(new)
    out = {**spec, "sequences": entries}
    if renamed and "placements" in spec:
        out["placements"] = [
            {**p, "sequences": [renamed.get(s, s) for s in p["sequences"]]}
            if p.get("sequences")
            else p
            for p in spec["placements"]
        ]
    return out


def idempotency_key(spec: dict[str, Any], dry_run: bool) -> str:
    """The submit's default Idempotency-Key: a digest of the resolved spec and dry_run."""
    text = json.dumps({"spec": spec, "dry_run": dry_run}, sort_keys=True, separators=(",", ":"))
    return "campaign-" + hashlib.sha256(text.encode()).hexdigest()[:40]


def _print_variants(body: dict[str, Any]) -> None:
    for v in body.get("variants", []):
        objs = []
        for o in v["objects"]:
            r = o["resolved"]
            where = (
                f"s={r['s_job_m']:.1f} m offset={r['offset_m']:+.2f} m"
                if r.get("s_job_m") is not None
                else f"xyz={r['xyz_world']}"
            )
            objs.append(
                f"{o['class_name']} #{o['variation_seed']} {r.get('zone') or 'explicit'} "
                f"{where} yaw={r['yaw_deg']:.1f} deg"
            )
        print(f"{v['id']} {v['key']} {v['sequence_label']}: {'; '.join(objs)}")  # noqa: T201


def follow(http: httpx.Client, campaign_id: str, *, poll_s: float = 2.0) -> dict[str, Any]:
    """Poll the campaign to its end with a progress bar over its frames; its last state."""
    bar = None
    try:
        while True:
            body = _check(
                http.get(f"/v1/campaigns/{campaign_id}", params={"variants_limit": 1}),
                "polling the campaign",
            )
            p = body["progress"]
            if p["frames_total"]:
                if bar is None:
                    bar = progress_bar(p["frames_total"], f"campaign {body['name']}")
                bar.n = p["frames_done"]
                bar.set_postfix_str(f"{p['succeeded']} ok {p['failed']} failed {body['state']}")
                bar.refresh()
            if body["state"] in TERMINAL:
                return body
            time.sleep(poll_s)
    finally:
        if bar is not None:
            bar.close()


def submit(args: argparse.Namespace) -> int:
    try:
        spec = load_campaign(args.spec)
    except CampaignRunError as exc:
        raise CliError(str(exc)) from exc
    data = spec.model_dump(mode="json", exclude_none=True)
    with _client(args) as http:
        try:
            data = resolve_sequences(http, data, Path.cwd())
            key = args.idempotency_key or idempotency_key(data, args.dry_run)
            r = http.post(
                "/v1/campaigns",
                json=data,
                params={"dry_run": args.dry_run},
                headers={"Idempotency-Key": key},
            )
            body = _check(r, f"submitting {args.spec}")
            cid = body["id"]
            where = f"{args.url.rstrip('/')}/v1/campaigns/{cid}"
            print(f"campaign {cid} {body['state']} ({where})", file=sys.stderr)  # noqa: T201
            if args.dry_run and body["state"] not in TERMINAL:
                body = follow(http, cid)
                body = _check(
                    http.get(f"/v1/campaigns/{cid}", params={"variants_limit": 1000}),
                    "reading the dry run",
                )
            elif args.wait:
                body = follow(http, cid)
        except httpx.HTTPError as exc:
            raise CliError(f"{args.url}: {exc}") from exc
    print(cid)  # noqa: T201 - CLI output (the id, for scripts)
    if args.dry_run:
        _print_variants(body)
        for issue in body.get("issues", []):
            print(f"{issue['level']}: {issue['where']}: {issue['message']}", file=sys.stderr)  # noqa: T201
    if body["state"] == "FAILED":
        raise CliError(f"campaign {cid} FAILED: {body.get('error')}")
    return 0


# ---------------------------------------------------------------------------- download
def _fetch(http: httpx.Client, url: str, dest: Path, size: int | None, bar: Any) -> None:
    """``url`` into ``dest`` via ``dest.partial``, resumed with Range (module docstring)."""
    if dest.is_file() and (size is None or dest.stat().st_size == size):
        if bar is not None and size:
            bar.update(size)
        return
    part = dest.with_name(dest.name + ".partial")
    have = part.stat().st_size if part.is_file() else 0
    if size is not None and have > size:
        part.unlink()
        have = 0
    headers = {"Range": f"bytes={have}-"} if have else {}
    if bar is not None and have:
        bar.update(have)
    if size is not None and have == size:
        part.replace(dest)
        return
    with http.stream("GET", url, headers=headers) as r:
        if r.status_code == 200 and have:  # the server sent it whole: start again
            part.unlink()
            if bar is not None:
                bar.update(-have)
            have = 0
        elif r.status_code not in (200, 206):
            r.read()
            _check(r, f"downloading {url}")
        with part.open("ab") as f:
            for chunk in r.iter_bytes(CHUNK):
                f.write(chunk)
                if bar is not None:
                    bar.update(len(chunk))
    if size is not None and part.stat().st_size != size:
        raise CliError(f"{url}: got {part.stat().st_size} bytes, expected {size} (run again)")
    part.replace(dest)


def download(args: argparse.Namespace) -> int:
    out: Path = args.out or Path("campaigns") / args.campaign_id
    cid = args.campaign_id
    with _client(args) as http:
        try:
            body = _check(
                http.get(f"/v1/campaigns/{cid}", params={"variants_limit": 1}), f"campaign {cid}"
            )
            if body["state"] not in TERMINAL and args.wait:
                body = follow(http, cid)
            if body["links"]["manifest_json"] is None:
                raise CliError(
                    f"campaign {cid} is {body['state']}: its manifest is written "
                    "when every variant has finished (use --wait)"
                )
            out.mkdir(parents=True, exist_ok=True)
            for name in ("manifest.json", "manifest.csv"):
                _fetch(http, f"/v1/campaigns/{cid}/{name}", out / name, None, None)
            manifest = json.loads((out / "manifest.json").read_text())
            rows = [r for r in manifest["variants"] if r["state"] == "done" and r["archive"]]
            total = sum(int(r["archive_bytes"] or 0) for r in rows)
            bar = progress_bar(total, f"campaign {manifest['campaign']}")
            bar.unit, bar.unit_scale = "B", True
            try:
                for r in rows:
                    dest = out / r["archive"]
                    dest.parent.mkdir(parents=True, exist_ok=True)
                    _fetch(http, f"/v1/jobs/{r['job_id']}/archive", dest, r["archive_bytes"], bar)
            finally:
                bar.close()
        except httpx.HTTPError as exc:
            raise CliError(f"{args.url}: {exc} (run again to resume)") from exc
    failed = [r for r in manifest["variants"] if r["state"] != "done"]
    print(  # noqa: T201
        f"{out}: manifest.json, manifest.csv and {len(rows)} archives "
        f"({total / 1e6:.1f} MB); {len(failed)} variants without one"
    )
    for r in failed:
        print(f"  {r['variant']} {r['state']}: {r.get('error')}")  # noqa: T201
    return 0


def run(args: argparse.Namespace) -> int:
    return {"submit": submit, "download": download}[args.campaign_command](args)


__all__ = ["download", "follow", "idempotency_key", "resolve_sequences", "run", "submit"]
