"""`octo-harness robustness --reliance-every N` (issue 45 item 1: reliance on `run` and `robustness`) and the position
controls: the grid's shared protocol carries the per-step measures, a protocol file's value holds unless a flag is
given, and a flag that would be refused by `run` is refused by the grid too."""

from __future__ import annotations

import pytest

from harness.cli import build_parser
from harness.cli.robustness import grid_protocol

BASE = ["robustness", "--model", "models/octo-reference-robosuite", "--task", "Lift", "--perturb", "camera"]


def _protocol(*extra: str):
    return grid_protocol(build_parser().parse_args([*BASE, *extra]))


def test_the_grid_protocol_carries_reliance_and_controls_only_when_asked():
    plain = _protocol()
    assert plain.policy.reliance_every == 0 and plain.policy.attention_controls is None
    measured = _protocol("--reliance-every", "4", "--reliance-fill", "blur", "--attention-controls", "blank")
    assert (measured.policy.reliance_every, measured.policy.reliance_fill) == (4, "blur")
    assert measured.policy.attention_controls == "blank" and measured.policy.controls_every == 1
    # a measure never changes actions, but it is part of what the run writes: the protocols differ
    assert measured.hash() != plain.hash()


def test_a_protocol_file_value_holds_unless_the_flag_is_given(tmp_path):
    path = tmp_path / "protocol.toml"
    path.write_text("reliance_every = 3\n")
    assert _protocol("--protocol", str(path)).policy.reliance_every == 3
    assert _protocol("--protocol", str(path), "--reliance-every", "5").policy.reliance_every == 5


def test_a_bad_reliance_value_is_refused_before_the_grid_starts():
    with pytest.raises(ValueError, match="--reliance-every"):
        _protocol("--reliance-every", "-1")
