"""`octo-harness sanity`: sanity checks of the attribution methods on recorded inputs (model-parameter randomisation,
patch additivity), once per policy."""

from __future__ import annotations

from pathlib import Path

from harness.options import add_arguments


def add_parser(sub) -> None:
    from harness.gate.sanity import SanityOptions

    san = sub.add_parser("sanity", help="sanity checks of the attribution methods, once per policy: model-parameter "
                                         "randomisation and patch additivity, open loop on recorded inputs",
                         description="On the inputs of runs made with --record-inputs: Spearman and SSIM between the "
                                     "maps of the trained policy and of the policy with re-drawn weights (cascading "
                                     "from the top block down, and each block alone), per method and camera, with "
                                     "95% intervals over steps and a pass/fail verdict; with --additivity also "
                                     "single-patch effects and their additivity per camera and fill. Writes "
                                     "sanity.json, randomisation.csv, additivity.csv; prints Markdown tables.")
    san.add_argument("runs", nargs="+", type=Path, metavar="RUN_DIR", help="run folder(s) made with --record-inputs "
                                                                           "(one policy; several tasks pool)")
    san.add_argument("--model", default=None, help="the policy to check [the runs' own model]")
    add_arguments(san, (SanityOptions,), "sanity")
    san.add_argument("--out", type=Path, default=None, help="output folder [first RUN_DIR/sanity]")
    san.set_defaults(func=main)


def main(args) -> int:
    from harness.gate.sanity import SanityOptions, markdown, run_sanity
    from harness.options import given

    options = SanityOptions(**given(SanityOptions, vars(args)))
    out = args.out or args.runs[0] / "sanity"
    result = run_sanity(args.runs, out, options, model_source=args.model)
    print(markdown(result))
    print(f"sanity: {out / 'sanity.json'} ({result['steps']} steps, {result['seconds']:.0f} s)")
    return 0
