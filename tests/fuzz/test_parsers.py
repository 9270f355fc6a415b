"""Property tests of the text a user types into options (hypothesis): whatever the text, each
parser returns a valid value or raises a one-line ``LabelsynthError`` naming its option, never
another exception (which the CLI would show as a traceback)."""

from __future__ import annotations

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from labelsynth.classes import ClassMap
from labelsynth.errors import LabelsynthError

SETTINGS = settings(max_examples=150, deadline=None, database=None, suppress_health_check=[HealthCheck.too_slow])
# texts near each grammar: its separators and digits, plus anything at all
GRAMMAR = st.text(alphabet="0123456789:,x=.-+eE naif", max_size=24)
ANY = st.text(max_size=24)
TEXT = st.one_of(GRAMMAR, ANY)


def _one_line(exc: BaseException, option: str) -> None:
    """The message names the option before any text the user typed (which may hold a line
    break; the CLI prints every message as one line, ``cli._one_line``)."""
    message = str(exc)
    assert message and option in message.splitlines()[0], message


def _parsers():
    from labelsynth.batch.run import check_address
    from labelsynth.capture.select import check_frame_spec
    from labelsynth.evaluation.bench import normalise_methods, normalise_perturbations
    from labelsynth.novel.poses import parse_spread
    from labelsynth.recipe import load_recipe
    from labelsynth.train.contract import parse_input_size
    from labelsynth.train.data import parse_class_weights
    from labelsynth.train.segment import parse_id_map

    classes = ClassMap.from_dict({"classes": [{"id": 0, "name": "background", "color": [0, 0, 0]},
                                              {"id": 1, "name": "wound", "color": [200, 40, 40], "wound_bed": True}]},
                                 "test")
    return {
        "--input-size": parse_input_size,
        "--id-map": parse_id_map,
        "--spread": parse_spread,
        "--class-weights": lambda t: parse_class_weights(t, classes),
        "--annotated-frames": check_frame_spec,
        "--address": check_address,
        "--methods": normalise_methods,
        "--perturb": normalise_perturbations,
        "--set": lambda t: load_recipe("fast", [t]),
    }


PARSERS = _parsers()


@pytest.mark.parametrize("option", sorted(PARSERS))
@SETTINGS
@given(text=TEXT)
def test_option_texts_parse_or_fail_in_one_line(option, text):
    try:
        PARSERS[option](text)
    except LabelsynthError as exc:
        if option == "--set":  # a recipe key's error names the key (fast.yaml.geometry.lr: ...), else --set
            assert str(exc).strip()
        else:
            _one_line(exc, option)


@SETTINGS
@given(value=st.one_of(st.integers(), st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=8),
                       st.booleans(), st.none()))
def test_numbers_are_checked_in_range_or_refused(value):
    from labelsynth.options import finite_number, seed_value, whole_number

    for check, option in ((lambda v: whole_number(v, "--n", 1, 10**6), "--n"), (seed_value, "--seed"),
                          (lambda v: finite_number(v, "--x", 0.0, 1.0, low_open=True), "--x")):
        try:
            result = check(value)
        except LabelsynthError as exc:
            _one_line(exc, option)
            continue
        assert result == result and abs(result) < 2**63  # neither NaN nor beyond 64 bits
