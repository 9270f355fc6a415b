"""Choosing frames by a short spec: which annotations teach (``annotated_frames``).

A capture may hold more expert masks than a run should learn from: a NeuS capture has an
exact object mask for every frame, and a benchmark wants a few to teach and the rest to score.
The spec is the same on the command line and in the library:

- ``a,b,c``: frame names (image stems) or 0-based indices into the frames sorted by name;
  a token that is a frame's name is that frame, otherwise it must be an index, so DTU's
  ``000003`` is a name and ``3`` the fourth frame;
- ``every:K``: frames 0, K, 2K, ...;
- ``spread:N``: N frames evenly spread over the sequence, each the middle of its N-th of it
  (the rule ``labelsynth synth`` uses to pick its annotated frames), so the ends are avoided.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from ..errors import CaptureError

FrameSpec = str | Sequence[str | int]


def select_frames(spec: FrameSpec, names: Sequence[str], where: str = "--annotated-frames") -> list[str]:
    """The names ``spec`` picks out of ``names`` (sorted frame names), in frame order.

    ``spec`` is a string as above, or a sequence of names and indices (what a run records;
    an empty one chooses no frame).
    A name that is not a frame, an index out of range or a malformed spec raises a one-line
    ``CaptureError`` starting with ``where``.
    """
    names = list(names)
    n = len(names)
    rule, tokens = _parse(spec, where)
    if rule == "every":
        return [names[i] for i in range(0, n, tokens)]
    if rule == "spread":
        if tokens > n:
            raise CaptureError(f"{where}: '{spec.strip()}' asks for {tokens} frames but the capture has {n}")
        return [names[i] for i in spread_indices(n, tokens)]
    index_of = {name: i for i, name in enumerate(names)}
    picked_set: set[int] = set()
    for token in tokens:
        if isinstance(token, str) and token in index_of:
            picked_set.add(index_of[token])
            continue
        try:
            i = int(token)
        except (TypeError, ValueError):
            shown = ", ".join(names[:3]) + (" ..." if n > 3 else "")
            raise CaptureError(f"{where}: no frame named '{token}' (frames: {shown}; or give 0-based indices)") from None
        if not 0 <= i < n:
            raise CaptureError(f"{where}: frame index {i} out of range (the capture has {n} frames, 0..{n - 1})")
        picked_set.add(i)
    return [names[i] for i in sorted(picked_set)]


def check_frame_spec(spec: FrameSpec, where: str = "--annotated-frames") -> None:
    """What can be checked of ``spec`` without the capture (its syntax), so that a run of many
    captures fails before the first one; names and indices are checked by ``select_frames``."""
    _parse(spec, where)


def _parse(spec: FrameSpec, where: str) -> tuple[str, Any]:
    """("every" | "spread", K) or ("frames", the tokens): the spec's syntax, checked."""
    if isinstance(spec, str):
        text = spec.strip()
        head, sep, arg = text.partition(":")
        if sep and head in ("every", "spread"):
            return head, _positive(arg, f"{where}: '{text}'")
        tokens = [t.strip() for t in text.split(",")]
        if any(t == "" for t in tokens):
            raise CaptureError(f"{where}: empty frame name in '{spec}' (use names, indices, every:K or spread:N)")
        return "frames", tokens
    if isinstance(spec, Sequence) and all(isinstance(t, (str, int)) and not isinstance(t, bool) for t in spec):
        return "frames", list(spec)  # may be empty: no annotation teaches
    raise CaptureError(f"{where}: expected names, indices, every:K or spread:N, not {type(spec).__name__}")


def spread_indices(n: int, k: int) -> list[int]:
    """``k`` indices evenly spread over ``n`` frames: the middle of each of ``k`` equal parts."""
    if k <= 0:
        return []
    return sorted({int((j + 0.5) * n / k) for j in range(k)})


def _positive(text: str, where: str) -> int:
    try:
        k = int(text)
    except ValueError:
        k = 0
    if k < 1:
        raise CaptureError(f"{where}: expected a whole number >= 1 after ':'")
    return k
