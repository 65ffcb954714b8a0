"""Every verdict a command prints or writes, as one family of string enums (issue 72 item 3).

`VerdictKind` is the family's base, a `StrEnum`. Each vocabulary is one subclass, and each of its members carries:
- its word, the member's value: what compare.json, regress.json, replay.json, sanity.json, a manifest's pre-flight
  findings and the console hold, unchanged (a member is a `str`, so files and f-strings show the word);
- its rank: the order the members are declared in, worst first (`rank`; `worst(verdicts)` of a vocabulary);
- its exit code: what a command that fails on it exits with (0: it never fails one). `fails_from` names the mildest
  choice of the command's option (`--fail-on`, `--preflight`) under which it fails; None: whenever its code is not 0;
- its one-line meaning, as docs/glossary.md defines it in the section `glossary` names
  (tests/docs/test_glossary.py holds the glossary to the family).

The vocabularies (`FAMILY`): `GateVerdict` (compare, regress), `Step0Verdict` (the model numerics at step 0 of
compare and regress), `ReplayVerdict` (replay), `PreflightVerdict` (run --preflight), `CellVerdict` (a robustness
grid's cells), `SanityVerdict` (the sanity check's randomisation test) and `Agreement` (the faithfulness report's open
and closed loop). A new verdict is one member line in its vocabulary, at its rank. `--fail-on`'s choices (`FAIL_ON`)
and the gate's exit codes (`gate_exit_code`) are derived from `GateVerdict`'s members.
"""
from __future__ import annotations

from enum import StrEnum, nonmember
from typing import Iterable

EXIT_OK, EXIT_FAIL, EXIT_INVALID, EXIT_ERRORED, EXIT_INCOMPLETE = 0, 1, 2, 3, 4


class VerdictKind(StrEnum):
    """The family's base: a member is (word, exit code, meaning[, fails_from]); its rank is its place, worst first."""

    def __new__(cls, word: str, exit_code: int, meaning: str, fails_from: str | None = None):
        member = str.__new__(cls, word)
        member._value_ = word
        member.exit_code = exit_code
        member.meaning = meaning
        member.fails_from = fails_from
        return member

    @property
    def rank(self) -> int:
        """0 for the vocabulary's worst verdict, one more for each milder one."""
        return type(self)._member_names_.index(self._name_)

    @classmethod
    def worst(cls, verdicts: Iterable[str]):
        """The worst of `verdicts` (members or their words); the vocabulary's mildest verdict for none."""
        return min((cls(v) for v in verdicts), key=lambda v: v.rank, default=cls[cls._member_names_[-1]])

    def fails(self, choice: str | None = None, choices: tuple[str, ...] = ()) -> bool:
        """Whether a command fails on this verdict under `choice`, one of `choices` (its option's choices, mildest
        first)."""
        if self.exit_code == EXIT_OK:
            return False
        return self.fails_from is None or choices.index(self.fails_from) <= choices.index(choice)


class GateVerdict(VerdictKind):
    """A gate verdict (compare, regress) of a task, the pooled table or the whole comparison."""

    glossary = nonmember("Gate verdicts")
    ERRORED = "ERRORED", EXIT_ERRORED, "an arm raised an error on more than half of its paired episodes"
    REGRESSED = ("REGRESSED", EXIT_FAIL, "the candidate succeeds less often, confirmed by McNemar's test "
                 "(Holm-adjusted) or, in regress, by its sequential test", "regressed")
    # below ERRORED and REGRESSED (a decided failure stands), above the rest (a gate is not passed by leaving work out)
    INCOMPLETE = "INCOMPLETE", EXIT_INCOMPLETE, "the candidate lacks finished episodes the baseline has"
    SUSPECT = ("SUSPECT", EXIT_FAIL, "the interval shows a drop that the exact test does not confirm", "suspect")
    UNDERPOWERED = "UNDERPOWERED", EXIT_FAIL, "none of the others: too few pairs to decide", "underpowered"
    HELD = ("HELD", EXIT_FAIL, "a drop larger than --max-drop (default 10 points) is ruled out, by the exact test or "
            "regress's sequential test", "changed")
    IMPROVED = ("IMPROVED", EXIT_FAIL, "the candidate succeeds more often, confirmed by McNemar's test "
                "(Holm-adjusted) or, in regress, by its sequential test", "changed")
    IDENTICAL = "IDENTICAL", EXIT_OK, "every array of every pair is bit-equal, with the same outcomes"


# --fail-on: the mildest verdict that fails the gate, mildest choice first; a choice also fails on every worse verdict
FAIL_ON = tuple(dict.fromkeys(v.fails_from for v in GateVerdict if v.fails_from))
DEFAULT_FAIL_ON = GateVerdict.SUSPECT.fails_from


def gate_exit_code(verdict: str, fail_on: str = DEFAULT_FAIL_ON) -> int:
    """Exit code of a gate verdict under --fail-on: ERRORED 3 and INCOMPLETE 4 whatever it is; 1 for a verdict
    from the one --fail-on names to the worst (REGRESSED; SUSPECT; UNDERPOWERED; anything but IDENTICAL); else 0."""
    if fail_on not in FAIL_ON:
        raise ValueError(f"unknown --fail-on {fail_on!r}; use one of {FAIL_ON}")
    verdict = GateVerdict(verdict)
    return verdict.exit_code if verdict.fails(fail_on, FAIL_ON) else EXIT_OK


class ReplayVerdict(VerdictKind):
    """replay's verdict: every inferred step within the tolerances, or not."""

    glossary = nonmember("Model numerics")
    CHANGED = "CHANGED", EXIT_FAIL, "a change beyond the tolerances: the model computes something else"
    EQUIVALENT = ("EQUIVALENT", EXIT_OK, "actions and attention differ, but within the replay tolerances (float "
                  "noise of another CPU)")


class Step0Verdict(VerdictKind):
    """The model numerics at step 0 of compare and regress, over the pairs that saw identical step-0 inputs."""

    glossary = nonmember("Model numerics")
    CHANGED = "CHANGED", EXIT_OK, ReplayVerdict.CHANGED.meaning
    UNKNOWN = ("UNKNOWN", EXIT_OK, "step 0 only: no pair saw identical step-0 inputs, so nothing could be "
               "compared")
    EQUIVALENT = "EQUIVALENT", EXIT_OK, ReplayVerdict.EQUIVALENT.meaning
    IDENTICAL = "IDENTICAL", EXIT_OK, "step 0 only: actions and attention are bit-equal"


class PreflightVerdict(VerdictKind):
    """The pre-flight check's verdict on one camera's frames or on the action space (run --preflight)."""

    glossary = nonmember("Pre-flight verdicts")
    MISMATCH = ("MISMATCH", EXIT_INVALID, "another image convention or action space fits better; the line names "
                "the flag to pass", "strict")
    INCONCLUSIVE = ("inconclusive", EXIT_OK, "the check cannot tell, for example from a blank example frame, and "
                    "says why")
    CONSISTENT = "consistent", EXIT_OK, "what the run feeds fits the checkpoint best, by the margin"


class CellVerdict(VerdictKind):
    """The verdict of one perturbed cell of a robustness grid against the nominal seeds."""

    glossary = nonmember("Robustness verdicts")
    BREAKS = "BREAKS", EXIT_OK, "the cell lost successes, and its Holm-adjusted McNemar p is at most 0.05"
    UNDETERMINED = ("UNDETERMINED", EXIT_OK, "neither: the data can tell neither a break nor the absence of one as "
                    "large as the margin")
    HOLDS = ("HOLDS", EXIT_OK, "not BREAKS, and a drop larger than the margin (--margin, default 15 points) is ruled "
             "out")


class SanityVerdict(VerdictKind):
    """An attribution method's verdict per camera in the model-parameter randomisation check (octo-harness sanity)."""

    glossary = nonmember("Faithfulness")
    FAIL = ("fail", EXIT_OK, "with every block's weights re-drawn, the upper 95% bound of the mean Spearman "
            "correlation with the trained map is 0.5 or more: the map does not depend on the weights")
    NOT_APPLICABLE = "n/a", EXIT_OK, "too few steps for an interval"
    PASS = ("pass", EXIT_OK, "with every block's weights re-drawn, the upper 95% bound of the mean Spearman "
            "correlation with the trained map is below 0.5")


class Agreement(VerdictKind):
    """Whether the open and the closed loop reach the same verdict on a camera's map (the Faithfulness section)."""

    glossary = nonmember("Faithfulness")
    DISAGREE = ("DISAGREE", EXIT_OK, "the open loop (deletion against random) and the closed loop (masking the "
                "map's top patches against random ones) reach different verdicts on a camera's map")
    AGREE = "agree", EXIT_OK, "the open loop and the closed loop reach the same verdict on a camera's map"


FAMILY = (GateVerdict, Step0Verdict, ReplayVerdict, PreflightVerdict, CellVerdict, SanityVerdict, Agreement)
