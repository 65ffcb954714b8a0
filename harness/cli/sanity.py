"""`octo-harness sanity`: sanity checks of the attribution methods on recorded inputs (model-parameter randomisation,
patch additivity), once per policy."""

from __future__ import annotations

from pathlib import Path


def add_parser(sub) -> None:
    san = sub.add_parser("sanity", help="sanity checks of the attribution methods, once per policy: model-parameter "
                                         "randomisation and patch additivity, open loop on recorded inputs",
                         description="On the inputs of runs made with --record-inputs: Spearman and SSIM between the "
                                     "maps of the trained policy and of the policy with re-drawn weights (cascading "
                                     "from the top block down, and each block alone), per method and camera, with "
                                     "95%% intervals over steps and a pass/fail verdict; with --additivity also "
                                     "single-patch effects and their additivity per camera and fill. Writes "
                                     "sanity.json, randomisation.csv, additivity.csv; prints Markdown tables.")
    san.add_argument("runs", nargs="+", type=Path, metavar="RUN_DIR", help="run folder(s) made with --record-inputs "
                                                                           "(one policy; several tasks pool)")
    san.add_argument("--model", default=None, help="the policy to check [the runs' own model]")
    san.add_argument("--every", type=int, default=10, help="every k-th inferred step of each episode [10]")
    san.add_argument("--max-steps", type=int, default=None, help="at most N steps in all [every selected step]")
    san.add_argument("--methods", default=None,
                     help="attribution methods (as for run --attribution; random is always added) "
                          "[attention,rollout,grad-attention,saliency,occlusion]")
    san.add_argument("--additivity", action="store_true",
                     help="also measure single-patch effects and how additive they are, per camera and fill")
    san.add_argument("--fills", default=None, help="fills of the additivity measures, comma-separated [mean,blur,impute]")
    san.add_argument("--seed", type=int, default=0, help="seed of the re-drawn weights and the random orders [0]")
    san.add_argument("--out", type=Path, default=None, help="output folder [first RUN_DIR/sanity]")
    san.set_defaults(func=main)


def main(args) -> int:
    from harness.gate.sanity import DEFAULT_METHODS, SanityOptions, markdown, run_sanity

    fills = tuple(f.strip() for f in args.fills.split(",") if f.strip()) if args.fills else SanityOptions.fills
    options = SanityOptions(every=args.every, methods=args.methods or DEFAULT_METHODS, additivity=args.additivity,
                            fills=fills, seed=args.seed, max_steps=args.max_steps)
    out = args.out or args.runs[0] / "sanity"
    result = run_sanity(args.runs, out, options, model_source=args.model)
    print(markdown(result))
    print(f"sanity: {out / 'sanity.json'} ({result['steps']} steps, {result['seconds']:.0f} s)")
    return 0
