"""``osdar-ar campaign run`` end to end on a tiny synthetic sequence: a 2-variant campaign,
its manifest (JSON and CSV), the contact sheet, resuming, the dry run and spec errors."""

from __future__ import annotations

import csv
import json
import shutil
import tarfile
from pathlib import Path
from typing import Any

import pytest
import yaml
from PIL import Image

from worker.campaign.manifest import csv_columns, flatten_row
from worker.campaign.run import CampaignRunError, combined_gauge, load_campaign
from worker.cli import main

pytestmark = pytest.mark.gl

SEQ = {"scene": "fire_site", "frames": 6, "scale": 0.15, "lidar_density": 0.2, "seed": 3}
CAMERAS = ["rgb_center"]


def _spec(seq: Path, **kw: Any) -> dict[str, Any]:
    base: dict[str, Any] = {
        "name": "tiny",
        "seed": 11,
        "sequences": [{"path": str(seq), "name": "fire"}],
        "obstacles": [{"builtin": "person"}, {"builtin": "rock"}],
        "placements": [{"zone": "track", "distance_m": [20, 45]}],
        "job": {"cameras": CAMERAS, "lidar": True, "strategy": "auto"},
    }
    return {**base, **kw}


def _write(path: Path, spec: dict[str, Any]) -> Path:
    path.write_text(yaml.safe_dump(spec, sort_keys=False))
    return path


@pytest.fixture(scope="module")
def base(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from worker.synth.generator import SynthConfig, generate

    folder = tmp_path_factory.mktemp("campaign_run")
    generate(folder / "fire_camp", SynthConfig(**SEQ))
    return folder


@pytest.fixture(scope="module")
def seq(base: Path) -> Path:
    return base / "fire_camp"


@pytest.fixture(scope="module")
def cache(base: Path) -> Path:
    return base / "cache"


def _run(args: list[str], cache: Path) -> int:
    return main(["campaign", "run", *args, "--cache-dir", str(cache), "--workers", "1"])


@pytest.fixture(scope="module")
def campaign(base: Path, seq: Path, cache: Path) -> tuple[Path, Path]:
    """The 2-variant campaign run once: (spec file, output folder)."""
    spec = _write(base / "tiny.yaml", _spec(seq))
    out = base / "out"
    assert _run([str(spec), "--out", str(out)], cache) == 0
    return spec, out


def _manifest(out: Path) -> tuple[dict[str, Any], list[dict[str, str]]]:
    doc = json.loads((out / "manifest.json").read_text())
    with (out / "manifest.csv").open(newline="") as f:
        rows = list(csv.DictReader(f))
    return doc, rows


def test_the_campaign_runs_and_its_manifest_json_and_csv_agree(
    campaign: tuple[Path, Path],
) -> None:
    _, out = campaign
    doc, rows = _manifest(out)
    assert doc["campaign"] == "tiny" and doc["seed"] == 11
    assert doc["summary"]["variants"] == 2 and doc["summary"]["done"] == 2
    variants = doc["variants"]
    assert [v["variant"] for v in variants] == ["v0000", "v0001"]
    assert [v["objects"][0]["class"] for v in variants] == ["person", "rock"]
    assert [r["variant"] for r in rows] == ["v0000", "v0001"]
    # the CSV is the JSON flattened, cell for cell
    assert list(rows[0]) == csv_columns(CAMERAS)
    assert rows == [flatten_row(v, CAMERAS) for v in variants]
    for v, r in zip(variants, rows, strict=True):
        assert v["state"] == "done" and v["error"] is None
        pos = v["objects"][0]["position"]
        assert pos["zone"] == "track" and 20.0 <= pos["distance_first_view_m"] <= 45.0
        assert r["s_m"] == str(pos["s_m"]) and r["class"] == v["objects"][0]["class"]
        # gauge flags: on the track inside the gauge, so it intrudes where annotated
        g = v["gauge"]
        assert g is not None and g["annotated_frames"] > 0
        assert g["intrudes"] is True and g["lateral_distance_m"] < 0.0
        assert r["gauge_intrudes"] == "true"
        assert g["track_distance_min_m"] <= g["track_distance_max_m"]
        # AR quality per camera: the paper RPE / jitter and the confidence bound median
        q = v["quality"]["rgb_center"]
        assert q["rpe_px_mean"] is not None and q["rpe_px_mean"] >= 0.0
        assert q["jitter_px_mean"] is not None and q["bound_px_median"] is not None
        assert float(r["rgb_center_bound_px_median"]) == q["bound_px_median"]
        archive = out / v["archive"]
        assert archive.is_file() and archive.stat().st_size == v["archive_bytes"]
        assert (out / v["thumb"]).is_file()
        assert v["seconds"] > 0.0
    # nothing half-written is left behind
    assert not list(out.rglob("*.partial")) and not (out / ".work").exists()


def test_each_archive_is_a_jobs_archive_with_its_variant(campaign: tuple[Path, Path]) -> None:
    _, out = campaign
    doc, _ = _manifest(out)
    v = doc["variants"][1]
    with tarfile.open(out / v["archive"]) as tar:
        names = tar.getnames()
        top = names[0].split("/")[0]
        metrics = json.loads(tar.extractfile(f"{top}/metrics.json").read())  # type: ignore[union-attr]
        labels = next(n for n in names if n.endswith("_labels.json") and n.count("/") == 1)
        raw = json.loads(tar.extractfile(labels).read())  # type: ignore[union-attr]
    assert top == "fire_camp"
    assert metrics["variant"]["id"] == "v0001" and metrics["variant"]["key"] == v["key"]
    assert metrics["augmentation"]["object"]["class"] == "rock"
    assert "paper_rpe" in metrics["evaluation"]
    assert any("report/previews/" in n for n in names)
    objs = raw["openlabel"]["objects"].values()
    assert any(o["name"].startswith("rock_synthetic_") for o in objs)


def test_the_contact_sheet_has_one_tile_per_variant(campaign: tuple[Path, Path]) -> None:
    _, out = campaign
    with Image.open(out / "contact_sheet.png") as im:
        w, h = im.size
    with Image.open(out / "thumbs" / "v0000.png") as t:
        tw, th = t.size
    # two tiles side by side, one row, each with its label lines below the frame
    assert w >= 2 * tw and th < h < 2 * th + 100
    records = [json.loads((out / "records" / f"v000{i}.json").read_text()) for i in range(2)]
    for rec in records:
        assert rec["contact"]["camera"] == "rgb_center"
        assert rec["contact"]["bbox"] is not None  # the frame where the object is largest


def test_variant_ids_and_keys_are_deterministic(
    campaign: tuple[Path, Path], base: Path, cache: Path
) -> None:
    spec, out = campaign
    dry = base / "dry_again"
    assert _run([str(spec), "--out", str(dry), "--dry-run"], cache) == 0
    assert (dry / "variants.json").read_bytes() == (out / "variants.json").read_bytes()
    ids = [(v["id"], v["key"]) for v in json.loads((dry / "variants.json").read_text())]
    assert [i for i, _ in ids] == ["v0000", "v0001"] and len({k for _, k in ids}) == 2


def test_a_rerun_skips_complete_variants_and_redoes_a_broken_one(
    campaign: tuple[Path, Path], base: Path, cache: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    spec, out = campaign
    again = base / "rerun"
    shutil.copytree(out, again)
    doc, _ = _manifest(again)
    a0, a1 = (again / v["archive"] for v in doc["variants"])
    before = a0.stat().st_mtime_ns
    capsys.readouterr()
    assert _run([str(spec), "--out", str(again)], cache) == 0
    assert "2 complete before, 0 made" in capsys.readouterr().out
    assert a0.stat().st_mtime_ns == before
    # an archive cut short (an interrupted copy): that variant alone is made again
    a1.write_bytes(a1.read_bytes()[:100])
    assert _run([str(spec), "--out", str(again)], cache) == 0
    assert "1 complete before, 1 made" in capsys.readouterr().out
    assert a0.stat().st_mtime_ns == before
    doc2, rows2 = _manifest(again)
    assert [v["state"] for v in doc2["variants"]] == ["done", "done"]
    assert (again / doc2["variants"][1]["archive"]).stat().st_size > 100
    assert doc2["summary"]["skipped"] == 1 and len(rows2) == 2


def test_a_dry_run_prints_the_variants_and_makes_nothing(
    base: Path, seq: Path, cache: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    spec = _write(base / "dry.yaml", _spec(seq, objects_per_sequence=2))
    out = base / "dry"
    capsys.readouterr()
    assert _run([str(spec), "--out", str(out), "--dry-run"], cache) == 0
    text = capsys.readouterr().out
    assert "v0000" in text and "person #0 track s=" in text and "rock #0" in text
    assert sorted(p.name for p in out.iterdir()) == ["variants.json"]
    (v,) = json.loads((out / "variants.json").read_text())  # 2 objects, one variant
    assert [o["class_name"] for o in v["objects"]] == ["person", "rock"]


@pytest.mark.parametrize(
    ("change", "needle"),
    [
        ({"placements": [{"zone": "runway"}]}, "placements[0].zone: Input should be"),
        ({"sequences": [{"path": "no/such/folder"}]}, "sequences[0].path: 'no/such/folder'"),
        ({"sequences": [{"id": "3f2a9c51"}]}, "sequences[0]: id '3f2a9c51' names a sequence"),
        ({"draws": 0}, "draws: Input should be greater than or equal to 1"),
        ({"obstacles": [{"asset_id": "a81b3c"}]}, "obstacles[0]: asset_id 'a81b3c' names a"),
        (
            {"placements": [{"zone": "track", "distance_m": [400, 500]}]},
            "placements[0] on fire: distance_m 400-500 m",
        ),
    ],
)
def test_an_invalid_spec_is_a_one_line_error_naming_the_file_and_field(
    base: Path,
    seq: Path,
    cache: Path,
    capsys: pytest.CaptureFixture[str],
    change: dict[str, Any],
    needle: str,
) -> None:
    spec = _write(base / "bad.yaml", _spec(seq, **change))
    out = base / "bad_out"
    capsys.readouterr()
    assert _run([str(spec), "--out", str(out)], cache) == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert err.startswith("osdar-ar campaign: error: ") and str(spec) in err
    assert needle in err
    assert not (out / "archives").exists()


def test_a_spec_file_that_is_not_yaml_or_json(tmp_path: Path) -> None:
    bad = tmp_path / "broken.json"
    bad.write_text('{"name": "x", ')
    with pytest.raises(CampaignRunError, match=r"broken.json: not valid JSON"):
        load_campaign(bad)
    listy = tmp_path / "list.yaml"
    listy.write_text("- a\n- b\n")
    with pytest.raises(CampaignRunError, match="a campaign spec is a mapping"):
        load_campaign(listy)


def test_an_interrupted_run_keeps_what_is_done_and_resumes(
    base: Path,
    seq: Path,
    cache: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    import worker.campaign.run as run_module

    spec = _write(base / "interrupted.yaml", _spec(seq, name="interrupted"))
    out = base / "interrupted"
    real = run_module.run_variant

    def killed_at_the_second(v: Any, *args: Any, **kw: Any) -> Any:
        if v.id == "v0001":
            raise KeyboardInterrupt
        return real(v, *args, **kw)

    monkeypatch.setattr(run_module, "run_variant", killed_at_the_second)
    with pytest.raises(KeyboardInterrupt):
        run_module.run_campaign(load_campaign(spec), spec, out, cache_dir=cache, workers=1)
    doc, rows = _manifest(out)
    assert [v["state"] for v in doc["variants"]] == ["done", "pending"]
    assert [r["state"] for r in rows] == ["done", "pending"]
    assert not (out / "records" / "v0001.json").exists() and not (out / ".work").exists()
    # what a kill -9 inside the archive's writing would leave: a .partial and scratch
    partial = out / "archives" / "v0001_fire_rock.tar.gz.partial"
    partial.write_bytes(b"half")
    (out / ".work" / "v0001").mkdir(parents=True)
    monkeypatch.setattr(run_module, "run_variant", real)
    capsys.readouterr()
    assert _run([str(spec), "--out", str(out)], cache) == 0
    assert "1 complete before, 1 made" in capsys.readouterr().out
    assert not partial.exists() and not (out / ".work").exists()
    doc, _ = _manifest(out)
    assert [v["state"] for v in doc["variants"]] == ["done", "done"]


def test_several_objects_and_a_walker_in_one_variant(base: Path, seq: Path, cache: Path) -> None:
    """objects_per_sequence 2 with a person crossing the track: one variant, both objects
    annotated in its labels, the walker's motion and speed in the manifest."""
    spec = _write(base / "multi.yaml", _spec(
        seq, objects_per_sequence=2,
        obstacles=[{"builtin": "person", "motion": {"pattern": "cross", "speed_mps": [1.2, 1.2],
                                                    "span_m": 6}},
                   {"builtin": "rock"}],
        constraints={"min_spacing_m": 2.0},
    ))  # fmt: skip
    out = base / "multi_out"
    assert _run([str(spec), "--out", str(out)], cache) == 0
    doc, rows = _manifest(out)
    (row,) = doc["variants"]
    assert row["state"] == "done", row["error"]
    walker, rock = row["objects"]
    assert walker["speed_mps"] == 1.2 and walker["motion"]["mode"] == "track"
    assert rock["speed_mps"] is None and rock["motion"] is None
    assert walker["gauge"] is not None and rock["gauge"] is not None
    assert rows[0]["objects"] == "2" and rows[0]["speed_mps"] == "1.2;"
    with tarfile.open(out / row["archive"]) as tar:
        labels = next(m for m in tar.getmembers() if m.name.endswith("_labels.json"))
        raw = json.loads(tar.extractfile(labels).read())["openlabel"]
    synthetic = [o for o in raw["objects"].values() if "_synthetic_" in o["name"]]
    assert sorted(o["name"] for o in synthetic) == ["person_synthetic_0001",
                                                    "rock_synthetic_0002"]  # fmt: skip
    speeds = {
        a["val"]
        for fr in raw["frames"].values()
        for ob in (fr.get("objects") or {}).values()
        for cub in ob["object_data"].get("cuboid", [])
        for a in cub["attributes"]["num"]
        if a["name"] == "speedMps"
    }
    assert speeds == {0.0, 1.2}
    assert Image.open(out / "contact_sheet.png").size[0] > 100


def test_the_gauge_over_several_objects_intrudes_when_any_does() -> None:
    a = {
        "intrusion_frames": 0,
        "annotated_frames": 6,
        "lateral_distance_m": 0.4,
        "track_distance_m": [20.0, 25.0],
        "outline": {"margin_m": 0.2},
    }
    b = {"intrusion_frames": 4, "annotated_frames": 5, "lateral_distance_m": -1.1,
         "track_distance_m": [31.0, 35.5], "outline": {"margin_m": 0.2}}  # fmt: skip
    g = combined_gauge([a, None, b])
    assert g is not None
    assert g["intrusion_frames"] == 4 and g["objects_intruding"] == 1
    assert g["lateral_distance_m"] == -1.1 and g["track_distance_m"] == [20.0, 35.5]
    assert combined_gauge([a]) == a and combined_gauge([None, None]) is None
