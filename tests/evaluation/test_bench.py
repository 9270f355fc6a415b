"""`labelsynth bench` on a tiny synthetic capture: schema, tables, plot, errors.

Quality is irrelevant here (a few iterations on 64x48 frames); the full-size run lives in
benchmarks/bench_paper_tables.py.
"""

import json
import shutil

import pytest
from typer.testing import CliRunner

from labelsynth.classes import ClassMap
from labelsynth.cli import app
from labelsynth.errors import LabelsynthError
from labelsynth.evaluation.bench import _bold_table, bench_markdown, normalise_methods, normalise_perturbations, run_bench
from labelsynth.evaluation.perturb import PERTURBATIONS
from labelsynth.evaluation.synth import SynthConfig, synthesize

TINY = [
    "geometry.iterations=30",
    "semantic.iterations=20",
    "render.mesh_resolution=64",
    "geometry.target_samples=2048",
    "geometry.max_rays=512",
    "geometry.march_steps=64",
    "geometry.occupancy_resolution=32",
    "semantic.rays_per_batch=512",
    "semantic.max_rays_per_frame=2000",
]


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    root = tmp_path_factory.mktemp("bench")
    return synthesize(root / "synth", SynthConfig(frames=6, annotated=2, width=64, height=48), progress=False)


@pytest.fixture(scope="module")
def cli_run(tiny, tmp_path_factory):
    """One full bench run through the CLI, shared by the schema/table/plot tests."""
    out = tmp_path_factory.mktemp("bench_out") / "out"
    args = ["bench", str(tiny.capture_dir), "--truth", str(tiny.truth_dir), "--out", str(out),
            "--recipe", "fast", "--device", "cpu"]
    for o in TINY:
        args += ["--set", o]
    result = CliRunner().invoke(app, args)
    return result, out


def test_cli_bench_succeeds_and_prints_tables(cli_run):
    result, out = cli_run
    assert result.exit_code == 0, result.output
    assert "Table 1" in result.output and "Table 2" in result.output
    assert (out / "bench.json").is_file() and (out / "bench.md").is_file() and (out / "bench.png").is_file()


def test_bench_json_schema(cli_run, tiny):
    _, out = cli_run
    data = json.loads((out / "bench.json").read_text())
    classes = ["wound_bed", *ClassMap.default().names]
    expected = {("2d", "predictions", p) for p in PERTURBATIONS if p != "half-frames"}
    expected |= {("3d2d", "predictions", p) for p in PERTURBATIONS}
    expected |= {("field", "predictions", p) for p in PERTURBATIONS}
    expected |= {("field", "annotations", "none")}
    got = {(r["method"], r["labels"], r["perturbation"]) for r in data["rows"]}
    assert got == expected
    for combo in expected:
        rows = [r for r in data["rows"] if (r["method"], r["labels"], r["perturbation"]) == combo]
        assert sorted(r["class"] for r in rows) == sorted(classes)
        for r in rows:
            assert isinstance(r["n"], int) and 0 <= r["n"] <= 4  # 6 frames, 2 annotated -> 4 scored
            for m in ("dice", "recall"):
                if r["n"] == 0:
                    assert r[m] is None
                else:
                    assert 0.0 <= r[m] <= 1.0
    # the wound is in every frame's truth: the wound-bed population is every scored frame
    wb = [r for r in data["rows"] if r["class"] == "wound_bed"]
    assert all(r["n"] == 4 for r in wb)
    assert set(data["seconds"]) == {"2d", "3d2d", "field"}
    assert all(v >= 0 for v in data["seconds"].values())
    assert data["scored_frames"] == 4 and sorted(data["annotated_frames"]) == sorted(tiny.annotated)
    assert data["half_frames_geometry"] == "refit on kept frames"


def test_bench_md_tables_and_png(cli_run):
    _, out = cli_run
    md = (out / "bench.md").read_text()
    assert "## Table 1" in md and "## Table 2" in md
    assert "| Method | Wound Bed DSC | Recall | Granulation DSC | Recall | Slough DSC | Recall |" in md
    for name in ("| 2D |", "| 3D/2D |", "| Field |", "| Field (annotations) |"):
        assert name in md
    assert "Half the frames" in md and "Jittering" in md and "Erosion-Dilation" in md
    assert "| 2D | Half the frames" not in md  # as in the paper: 2D has no half-frames row
    assert "**" in md
    assert (out / "bench.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_run_bench_library_2d_only(tiny, tmp_path):
    """The 2D rows need no fitting at all: a quick check of the library call and its return value."""
    res = run_bench(tiny.capture_dir, tiny.truth_dir, tmp_path / "o", methods="2d",
                    perturbations=["none", "jitter"], recipe="fast", device="cpu", progress=False)
    assert {(r["method"], r["perturbation"]) for r in res["rows"]} == {("2d", "none"), ("2d", "jitter")}
    assert json.loads((tmp_path / "o" / "bench.json").read_text())["rows"] == res["rows"]
    # the unperturbed 2D score is the predictions' own score
    none_wb = next(r for r in res["rows"] if r["perturbation"] == "none" and r["class"] == "wound_bed")
    assert 0.0 < none_wb["dice"] <= 1.0


def test_missing_truth_folder_and_file(tiny, tmp_path):
    with pytest.raises(LabelsynthError, match="truth folder not found"):
        run_bench(tiny.capture_dir, tmp_path / "nope", tmp_path / "o", methods="2d", progress=False)
    truth = tmp_path / "truth"
    shutil.copytree(tiny.truth_dir, truth)
    scored = sorted(p.stem for p in truth.glob("*.png") if p.stem not in tiny.annotated)
    (truth / f"{scored[0]}.png").unlink()
    with pytest.raises(LabelsynthError, match=f"{scored[0]}.png: truth mask missing"):
        run_bench(tiny.capture_dir, truth, tmp_path / "o", methods="2d", progress=False)
    # annotated frames are never scored, so their truth may be absent
    truth2 = tmp_path / "truth2"
    shutil.copytree(tiny.truth_dir, truth2)
    (truth2 / f"{tiny.annotated[0]}.png").unlink()
    run_bench(tiny.capture_dir, truth2, tmp_path / "o2", methods="2d", perturbations="none", progress=False)
    # the CLI turns it into one line and exit code 2
    r = CliRunner().invoke(app, ["bench", str(tiny.capture_dir), "--truth", str(truth), "--out", str(tmp_path / "o3"),
                                 "--methods", "2d"])
    assert r.exit_code == 2
    assert "truth mask missing" in r.output and len(r.output.strip().splitlines()) == 1


def test_list_options():
    assert normalise_methods("3D/2D, field,2d") == ["2d", "3d2d", "field"]
    assert normalise_methods(None) == ["2d", "3d2d", "field"]
    assert normalise_perturbations("jitter,none") == ["none", "jitter"]
    assert normalise_perturbations("half_frames") == ["half-frames"]
    with pytest.raises(LabelsynthError, match="unknown bench method"):
        normalise_methods("segformer")
    with pytest.raises(LabelsynthError, match="unknown perturbation"):
        normalise_perturbations("blur")


def test_bold_marks_best_per_column_with_ties():
    cells = _bold_table([[0.5, 0.9], [0.7, 0.9], [None, 0.1]])
    assert cells == [["0.500", "**0.900**"], ["**0.700**", "**0.900**"], ["-", "0.100"]]


def test_markdown_without_field_rows():
    result = {
        "rows": [{"method": "2d", "labels": "predictions", "perturbation": "none", "class": c, "dice": 0.8,
                  "recall": 0.7, "precision": 0.9, "iou": 0.6, "n": 3} for c in ("wound_bed", "granulation")],
        "seconds": {"2d": 0.1}, "timing": {"total": 1.0}, "capture": "c", "truth": "t", "recipe": "fast",
        "device": "cpu", "seed": 0, "methods": ["2d"], "perturbations": ["none"], "frames": 5,
        "annotated_frames": ["a"], "scored_frames": 4, "half_frames_kept": 3, "half_frames_geometry": "shared",
        "fusion": {"cutoff_deg": 75.0, "stride": 2, "mesh": "fitted field"}, "notes": [],
    }
    md = bench_markdown(result)
    assert "| 2D | 0.800 | 0.700 | 0.800 | 0.700 |" in md  # a lone row is not bold
