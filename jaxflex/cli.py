"""``jaxflex <command>``: the command-line edge (argparse lives only here)."""

from __future__ import annotations

import argparse
import sys
import time
from typing import Sequence


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer >= 1; got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected an integer >= 1; got {value}")
    return value


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="jaxflex", description="Differentiable simulator and tuner for vibration control of flexible manipulators.")
    sub = parser.add_subparsers(dest="command", required=True)
    rep = sub.add_parser("reproduce", help="reproduce the paper: three runs, figures, report.md, results.json")
    rep.add_argument("--out", default="results", help="output folder (default: ./results)")
    rep.add_argument("--modes", type=_positive_int, default=2, help="number of assumed modes, >= 1 (default: 2, as the paper)")
    rep.add_argument("--x64", action="store_true", help="simulate in float64 (default float32)")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``jaxflex`` console script."""
    args = _parser().parse_args(argv)
    if args.x64:
        import jax

        jax.config.update("jax_enable_x64", True)
    if args.command == "reproduce":
        from jaxflex.report import reproduce

        start = time.perf_counter()

        def progress(msg: str) -> None:
            print(f"[{time.perf_counter() - start:6.1f} s] {msg}", file=sys.stderr, flush=True)

        try:
            results = reproduce(args.out, n_modes=args.modes, progress=progress)
        except ValueError as err:
            print(f"jaxflex reproduce: error: {err}", file=sys.stderr)
            return 2
        freqs = ", ".join(f"{f:.2f}" for f in results["model"]["natural_frequencies_hz"][:2])
        db = results["vibration_reduction_db"]
        print(f"model natural frequencies: {freqs} Hz (paper: 16, 55 Hz)")
        print(f"vibration reduction (dB, {results['psd']['name']}): DFS {db['dfs']}, fuzzy {db['fuzzy']}")
        print(f"wrote {args.out}/results.json, {args.out}/report.md and figures in {args.out}/ ({time.perf_counter() - start:.1f} s)")
        return 0
    return 2  # pragma: no cover - argparse enforces the choices


if __name__ == "__main__":
    sys.exit(main())
