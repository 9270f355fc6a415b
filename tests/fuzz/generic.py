"""Malformed values for every option of every command, generated from the CLI's own definition
(so a command or option added later is fuzzed too, or ``test_every_option_is_covered`` fails).

Each command has a SPEC: a valid invocation that reaches its long work (``test_the_valid_
invocations_reach_the_long_work`` proves it), and the role of each path (an input folder, an
input file, an output). Every option is then given values of the wrong type, empty, out of
range, huge, NaN and infinite numbers, and for paths: missing, the wrong kind (a file for a
folder and back), zero-byte, a symlink loop, a non-UTF-8 name, an output inside a file, an
output that is the capture itself, an unwritable output.

The rules checked on all of them: an integer option takes no text, fraction, negative number or
number beyond 64 bits; a number option takes no text, NaN or infinity; a text option takes no
empty text; a flag takes no value.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field

import torch
import typer

from labelsynth.cli import app

from .harness import Case, deny_writes_under
from .world import World

HUGE = "9" * 30  # beyond any 64-bit integer


@dataclass
class Spec:
    base: list[str]
    """A valid invocation (placeholders: ``World.names``)."""
    paths: dict[str, str] = field(default_factory=dict)
    """Parameter name -> ``dir`` (an input folder), ``file`` (an input file), ``file-or-dir``, ``out``."""
    free_text: tuple[str, ...] = ()
    """Text options where any non-empty text may be valid (not fuzzed with junk)."""


SPECS: dict[str, Spec] = {
    "synth": Spec(["synth", "{out}", "--frames", "4", "--annotated", "2", "--width", "32", "--height", "32"],
                  {"out": "out"}),
    "poses": Spec(["poses", "{cap}", "--out", "{out}"], {"capture": "dir", "out": "out"}),
    "import": Spec(["import", "{video}", "--out", "{out}", "--frames", "3"], {"source": "file-or-dir", "out": "out"}),
    "expand": Spec(["expand", "{cap}", "--out", "{out}", "--recipe", "fast", "--device", "cpu"],
                   {"capture": "dir", "out": "out", "geometry": "file-or-dir"}),
    "batch": Spec(["batch", "{cap}", "--out", "{out}", "--recipe", "fast", "--device", "cpu"],
                  {"source": "file-or-dir", "out": "out"}, free_text=("annotated_frames",)),
    "suggest": Spec(["suggest", "{cap}", "--annotate", "2", "--out", "{out}", "--recipe", "fast", "--device", "cpu"],
                    {"capture": "dir", "out": "out"}),
    "report": Spec(["report", "{run}", "--device", "cpu", "--no-loo"], {"out": "dir"}),
    "demo": Spec(["demo", "--out", "{out}", "--frames", "4", "--device", "cpu"], {"out": "out"}),
    "segment": Spec(["segment", "{cap}", "--model", "{model}", "--out", "{out}", "--device", "cpu"],
                    {"capture": "dir", "model": "file", "out": "out"}),
    "train": Spec(["train", "{cap}", "{h5}", "--out", "{out}", "--steps", "1", "--batch-size", "1", "--crop", "32",
                   "--device", "cpu"], {"sources": "file-or-dir", "out": "out", "init": "file-or-dir"}),
    "selftrain": Spec(["selftrain", "{cap}", "--model", "{model}", "--out", "{out}", "--rounds", "1", "--steps", "1",
                       "--batch-size", "1", "--crop", "32", "--recipe", "fast", "--device", "cpu"],
                      {"captures": "dir", "model": "file", "out": "out", "holdout": "dir", "also": "file-or-dir"}),
    "export": Spec(["export", "{run}", "--format", "coco", "--to", "{out}"], {"out": "dir", "to": "out"}),
    "relabel": Spec(["relabel", "{run}", "--device", "cpu", "--no-report"], {"out": "dir", "capture": "dir"}),
    "augment": Spec(["augment", "{run}", "--views", "1", "--device", "cpu"], {"out": "dir", "capture": "dir"}),
    "bench": Spec(["bench", "{cap}", "--truth", "{truth}", "--out", "{out}", "--recipe", "fast", "--device", "cpu"],
                  {"capture": "dir", "truth": "dir", "out": "out", "mesh": "file"}),
}


def commands() -> dict[str, typer.core.TyperCommand]:
    return dict(typer.main.get_command(app).commands)


def _kind(param) -> str:
    ann = param.type_descriptor.annotation
    text = getattr(ann, "__name__", str(ann))
    if getattr(param, "is_flag", False):
        return "flag"
    if "Path" in str(ann):
        return "path"
    return {"int": "int", "float": "float", "str": "str"}.get(text, "str" if "str" in str(ann) else text)


def _with(base: list[str], param, value: str) -> list[str]:
    """``base`` with ``param`` given ``value`` (an option appended: click keeps the last one;
    an argument replacing its placeholder)."""
    if param.param_type_name == "option":
        return [*base, param.opts[0], value]
    positions = [i for i, a in enumerate(base[1:], 1) if a.startswith("{") and not base[i - 1].startswith("--")]
    index = [p.name for p in commands()[base[0]].params if p.param_type_name == "argument"].index(param.name)
    argv = list(base)
    argv[positions[index]] = value  # SOURCE...: the malformed one first, the good ones after it
    return argv


def _make_file(name: str, data: bytes):
    def setup(world: World) -> None:
        (world.root / name).write_bytes(data)

    return setup


def _make_loop(world: World) -> None:
    os.symlink("loop", world.root / "loop")


def _make_dir(world: World) -> None:
    (world.root / "empty_dir").mkdir()


def _path_cases(cmd: str, spec: Spec, param, role: str) -> list[Case]:
    base = spec.base
    label = param.opts[0] if param.param_type_name == "option" else param.name.upper()
    bad = []
    if role in ("dir", "file", "file-or-dir"):
        bad += [
            ("missing", "{root}/missing", None, ("{root}/missing",)),
            ("loop", "{root}/loop", _make_loop, ("{root}/loop",)),
            ("non-utf8", os.fsdecode(b"{root}/caf\xe9"), None, ("{root}/caf",)),
            ("zero-byte", "{root}/zero.bin", _make_file("zero.bin", b""), ("{root}/zero.bin",)),
            ("junk", "{root}/junk.txt", _make_file("junk.txt", b"\x00\xffnot what it claims\n"), ("{root}/junk.txt",)),
        ]
    if role in ("dir", "file-or-dir"):
        bad.append(("empty-dir", "{root}/empty_dir", _make_dir, ("{root}/empty_dir",)))
    if role == "file":
        bad.append(("a-folder", "{root}/empty_dir", _make_dir, ("{root}/empty_dir",)))
    if role == "out":
        bad += [
            ("inside-a-file", "{root}/junk.txt/sub", _make_file("junk.txt", b"x"), ("{root}/junk.txt",)),
            ("a-file", "{root}/junk.txt", _make_file("junk.txt", b"x"), ("{root}/junk.txt",)),
            ("loop", "{root}/loop", _make_loop, ("{root}/loop",)),
            ("the-capture", "{cap}", None, ("{cap}",)),
        ]
    cases = []
    for tag, value, setup, expect in bad:
        if cmd == "poses" and param.name == "out" and tag == "the-capture":
            continue  # poses --out CAPTURE is CAPTURE/transforms.json: refused because it exists (below)
        cases.append(Case(f"{cmd}-{label}-{tag}", _with(base, param, value), expect, setup=setup))
    if role == "out":
        cases.append(Case(f"{cmd}-{label}-unwritable", _with(base, param, "{root}/locked/out"), ("{root}/locked",),
                          setup=lambda w: (w.root / "locked").mkdir(),
                          patch=deny_writes_under(lambda w: w.root / "locked"), keep=()))
    return cases


def generic_cases() -> list[Case]:
    cases: list[Case] = []
    for cmd, command in commands().items():
        spec = SPECS.get(cmd)
        if spec is None:
            continue  # test_every_option_is_covered names it
        for param in command.params:
            kind = _kind(param)
            name = param.opts[0] if param.param_type_name == "option" else param.name
            if kind == "flag":
                if param.param_type_name == "option":
                    cases.append(Case(f"{cmd}-{name}=value", [*spec.base, f"{name}=maybe"], (name,)))
                continue
            if kind == "path":
                role = spec.paths.get(param.name)
                if role is not None:
                    cases += _path_cases(cmd, spec, param, role)
                continue
            if param.param_type_name != "option":
                continue
            values = {
                "int": ["abc", "1.5", "", "-7", HUGE],
                "float": ["abc", "", "nan", "inf", "-inf"],
                "str": [""] + ([] if param.name in spec.free_text else ["%%"]),
            }.get(kind, [""])
            if param.name == "device" and not torch.cuda.is_available():
                values.append("cuda")  # asked for, not here: refused before any work
            for value in values:
                cases.append(Case(f"{cmd}-{name}={value or 'empty'}"[:80], _with(spec.base, param, value), (name,)))
    return cases
