"""`octo-harness replay`: a model open loop on the inputs a run recorded (--record-inputs), its actions and
attention compared with the run's (EQUIVALENT exit 0, CHANGED exit 1)."""

from __future__ import annotations

from pathlib import Path

from harness.cli.common import add_gate_options, writing


def add_parser(sub) -> None:
    rp = sub.add_parser("replay", help="run a model open loop on the inputs a run recorded (--record-inputs) and "
                                       "compare its actions and attention with the run's",
                        description="The model change isolated from the simulator and the platform: EQUIVALENT (every "
                                    "inferred step within the tolerances) exit 0, CHANGED exit 1, invalid input or "
                                    "replay.json not written exit 2.")
    rp.add_argument("run", type=Path, metavar="RUN_DIR", help="a run made with --record-inputs (e.g. a committed baseline)")
    rp.add_argument("--model", default=None, help="the model to replay [the run's own model]")
    add_gate_options(rp, "replay", ("action_tolerance", "attention_tolerance", "drop_probes"))
    rp.add_argument("--out", type=Path, default=None, help="output folder for replay.json [RUN_DIR/replay]")
    rp.set_defaults(func=main)


def main(args) -> int:
    from harness.gate.config import GateConfig
    from harness.files import atomic_write_json
    from harness.gate.replay import exit_code, replay_run, summary_text

    gate = GateConfig.from_args(args)
    gate.tolerances()  # bad tolerances: one line, before the run is read
    result = replay_run(args.run, args.model, gate)
    out = args.out or args.run / "replay"
    writing(f"{out / 'replay.json'}", result.verdict, lambda: atomic_write_json(out / "replay.json", result.to_json()))
    print(summary_text(result))
    print(f"replay: {out / 'replay.json'}")
    return exit_code(result)
