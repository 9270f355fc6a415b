"""The fuzz suite over the whole CLI (``harness`` states the properties every case must have).

``generic``: every option of every command with malformed values, generated from the CLI's own
definition; ``files``: malformed files inside the inputs. The valid invocations they start from
are checked to reach each command's long work, so a case fails for its one malformed thing.
"""

from __future__ import annotations

import shutil

import pytest
import torch
from typer.testing import CliRunner

from labelsynth.cli import app

from . import files
from .files import Payload, file_cases
from .generic import SPECS, commands, generic_cases
from .harness import Case, Reached, patch_heavy, run_case
from .world import World

CASES: list[Case] = generic_cases() + file_cases()


@pytest.fixture(scope="session")
def fuzz_world(tmp_path_factory) -> World:
    return World.build(tmp_path_factory.mktemp("fuzz_world"))


@pytest.mark.parametrize("case", CASES, ids=[c.id for c in CASES])
def test_malformed(case, fuzz_world, tmp_path, monkeypatch):
    world = fuzz_world.copy(tmp_path / "w", checkpoint=case.checkpoint)
    run_case(case, world, monkeypatch)


def test_every_command_and_option_is_fuzzed():
    """A command added to the CLI (suggest, export, relabel, ...) needs a SPEC here, and every
    option of every command is given malformed values by at least one case."""
    missing = sorted(set(commands()) - set(SPECS))
    assert not missing, f"commands without a fuzz SPEC (tests/fuzz/generic.py): {missing}"
    for name, command in commands().items():
        covered = " ".join(" ".join(c.argv) for c in CASES if c.command == name)
        for param in command.params:
            if param.param_type_name == "option":
                assert param.opts[0] in covered, f"{name} {param.opts[0]}: no malformed case"
    assert len(CASES) >= 200


VALID = {  # (argv, the long work it must reach)
    "synth": (SPECS["synth"].base, "synth"),
    "poses": (SPECS["poses"].base, "poses"),
    "import-video": (SPECS["import"].base, "import-video"),
    "import-photos": (files.IMPORT_PHOTOS, "import-photos"),
    "expand": (SPECS["expand"].base, "expand"),
    "expand-geometry": (files.EXPAND_GEOMETRY, "expand"),
    "suggest": (SPECS["suggest"].base, "geometry"),
    "batch": (SPECS["batch"].base, "batch"),
    "batch-list": (files.BATCH, "batch"),
    "report": (SPECS["report"].base, "report"),
    "demo": (SPECS["demo"].base, "synth"),
    "segment": (SPECS["segment"].base, "segment"),
    "train": (SPECS["train"].base, "train"),
    "train-resume": (files.RESUME, "train"),
    "augment": (SPECS["augment"].base, "augment"),
    "export": (SPECS["export"].base, "export"),
    "selftrain": (SPECS["selftrain"].base, "segment"),
    "bench": (SPECS["bench"].base, "bench"),
}


@pytest.mark.parametrize("name", sorted(VALID))
def test_the_valid_invocations_reach_the_long_work(name, fuzz_world, tmp_path, monkeypatch):
    """The invocations every case breaks one thing of are valid: each gets past every check."""
    argv, heavy = VALID[name]
    world = fuzz_world.copy(tmp_path / "w", checkpoint=name == "train-resume")
    (world.root / "list.txt").write_text("capture\n")
    patch_heavy(monkeypatch)
    names = world.names()
    args = [a.format(**names) if "{" in a else a for a in argv]
    result = CliRunner().invoke(app, args)
    assert isinstance(result.exception, Reached) and str(result.exception) == heavy, result.output


@pytest.mark.parametrize("kind", ["field", "checkpoint"])
def test_a_file_that_would_run_code_runs_nothing(kind, fuzz_world, tmp_path):
    """The payload the tampered cases plant does run when unpickled without restriction (so
    those cases can fail), and labelsynth's readers refuse it without running it."""
    from labelsynth.errors import LabelsynthError
    from labelsynth.rundir import load_field
    from labelsynth.train.checkpoint import load_checkpoint

    source = fuzz_world.run / "field.pt" if kind == "field" else fuzz_world.ckpt_dir / "checkpoint.pt"
    path, target = tmp_path / source.name, tmp_path / "pwned.txt"
    shutil.copy(source, path)
    state = torch.load(path, weights_only=True)
    state["payload"] = Payload(str(target))
    torch.save(state, path)
    torch.load(path, weights_only=False)
    assert target.read_text() == "pwned"
    target.unlink()
    with pytest.raises(LabelsynthError) as err:
        (load_field if kind == "field" else load_checkpoint)(path)
    assert not target.exists()
    assert str(err.value).startswith(f"{path}: refused: it would call Python code") and "\n" not in str(err.value)
