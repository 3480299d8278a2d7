"""``msk bench``: run the benchmarks in :mod:`services.bench` and print each figure beside its same-run baseline."""

from __future__ import annotations

import argparse
import importlib
import json
import pkgutil
from dataclasses import asdict
from pathlib import Path
from types import ModuleType

from msk_core.errors import ConfigError
from services import bench


def _benchmarks() -> dict[str, ModuleType]:
    """The modules of services.bench with a NAME, a DESCRIPTION and run(quick=...), by NAME."""
    found = {}
    for info in pkgutil.iter_modules(bench.__path__):
        module = importlib.import_module(f"{bench.__name__}.{info.name}")
        if hasattr(module, "run") and hasattr(module, "NAME"):
            found[module.NAME] = module
    return dict(sorted(found.items()))


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("bench", help="run the speed/memory benchmarks", description=__doc__)
    parser.add_argument("names", nargs="*", help="benchmarks to run (default: all); see --list")
    parser.add_argument("--list", action="store_true", help="list the benchmarks and exit")
    parser.add_argument("--quick", action="store_true", help="fewer repetitions (smoke run)")
    parser.add_argument("--json", type=Path, default=None, help="also write the results to this JSON file")
    parser.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    available = _benchmarks()
    if args.list:
        for name, module in available.items():
            print(f"{name:24s} {module.DESCRIPTION}")
        return 0
    unknown = [n for n in args.names if n not in available]
    if unknown:
        raise ConfigError(f"unknown benchmark; available: {', '.join(available)}", field="names", value=unknown)
    selected = args.names or list(available)
    all_results = []
    failed = False
    for name in selected:
        print(f"== {name}: {available[name].DESCRIPTION}", flush=True)
        for result in available[name].run(quick=args.quick):
            all_results.append({"benchmark": name, **asdict(result), "ratio": result.ratio})
            verdict = "" if result.passed is None else ("  PASS" if result.passed else "  FAIL")
            baseline = (
                f"  | {result.baseline_name}: {result.baseline_value:.4g} {result.unit}  ratio {result.ratio:.3g}x"
                if result.baseline_name
                else ""
            )
            target = f"  target {result.target}" if result.target else ""
            print(f"  {result.name}: {result.value:.4g} {result.unit}{baseline}{target}{verdict}", flush=True)
            if result.details:
                print(
                    "    "
                    + ", ".join(
                        f"{k} {v:.4g}" if isinstance(v, float) else f"{k} {v}" for k, v in result.details.items()
                    ),
                    flush=True,
                )
            failed |= result.passed is False
    if args.json is not None:
        args.json.write_text(json.dumps(all_results, indent=2, default=str))
    return 1 if failed else 0
