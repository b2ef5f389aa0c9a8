"""Hybrid FMUs with linux64 and win64 binaries: export, fmpy validation, and the win64 wrapper run
under wine against the linux64 one (the same C host, tests/export/host/euler_host.c, compiled for
both; fixed-step explicit Euler).

    python benchmarks/bench_win64.py [--demo-hybrid fmubuilder-demo/vldm_hybrid.fmu]

Cases: the demo's hybrid (its spec and network, as embedded in the FMU `fmubuilder demo` wrote,
re-exported on the VLDM example built for linux64 and, with mingw-w64, for win64), and a hybrid of
the Reference FMU BouncingBall (its win64 DLL compiled from its sources) with a small random
network. Needs mingw-w64 and wine. The max relative difference is |a - b| / max(|a|, |b|, 1) over
every printed value (time, states, outputs) of every step.
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import zipfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import fmpy  # noqa: E402
from fmpy.validation import validate_fmu  # noqa: E402

from fmubuilder.export import HybridSpec, export_hybrid  # noqa: E402
from tests.export.test_wrapper import make_hybrid  # noqa: E402
from tests.export.win64_fmus import (build_hosts, example_with_win64, reference_with_win64,  # noqa: E402
                                     relative_difference, require_wine, run_host, unpacked, value_reference)
from tests.reference_fmus import reference_fmu  # noqa: E402


def demo_case(demo_hybrid: Path, folder: Path) -> Path:
    """The demo's spec and network on the VLDM example with both binaries."""
    folder.mkdir(parents=True)
    with zipfile.ZipFile(demo_hybrid) as archive:
        for name in ("hybrid_spec.json", "network.onnx"):
            (folder / name).write_bytes(archive.read(f"resources/fmubuilder_hybrid/{name}"))
    data = json.loads((folder / "hybrid_spec.json").read_text())
    original = example_with_win64("vldm", folder / "original")
    data["original_fmu"] = str(original)
    (folder / "hybrid_spec.json").write_text(json.dumps(data))
    return export_hybrid(HybridSpec.load(folder / "hybrid_spec.json"), folder / "vldm_hybrid.fmu")


def reference_case(folder: Path) -> Path:
    original = reference_with_win64(reference_fmu("BouncingBall"), folder / "original")
    return make_hybrid(folder, original, ["der(v)"], ["h", "v"], seed=1)[1]


def compare(fmu: Path, outputs: list[str], stop: float, step: float, hosts, folder: Path) -> dict:
    references = [value_reference(fmu, name) for name in outputs]
    fmu_dir = unpacked(fmu, folder / "unpacked")
    linux = run_host(hosts[0], fmu_dir, fmu, stop, step, references)
    windows = run_host(hosts[1], fmu_dir, fmu, stop, step, references, wine=require_wine())
    return {"rows": len(linux), "columns": linux.shape[1], "max_abs": float(abs(windows - linux).max()),
            "max_rel": relative_difference(windows, linux)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--demo-hybrid", type=Path, default=Path("fmubuilder-demo/vldm_hybrid.fmu"))
    parser.add_argument("--vldm-stop", type=float, default=1101.0, help="end of the VLDM run (the CADC cycle)")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="bench-win64-") as scratch:
        scratch = Path(scratch)
        hosts = build_hosts(scratch)
        cases = [("demo VLDM (NeuralFMU on der(speed))", demo_case(args.demo_hybrid, scratch / "demo"),
                  ["der(speed)", "acceleration", "energy"], args.vldm_stop, 0.01),
                 ("Reference BouncingBall (random 2-6-1 net on der(v))", reference_case(scratch / "ball"),
                  ["der(v)"], 3.0, 1e-3)]
        print("| hybrid | platforms | fmpy validate | Euler span | rows x columns | max abs diff | "
              "max rel diff |")
        print("|---|---|---|---|---|---|---|")
        for index, (name, fmu, outputs, stop, step) in enumerate(cases):
            problems = validate_fmu(str(fmu))
            platforms = ", ".join(sorted(set(fmpy.supported_platforms(str(fmu))) - {"c-code"}))
            result = compare(fmu, outputs, stop, step, hosts, scratch / f"run{index}")
            print(f"| {name} | {platforms} | {'passed' if not problems else '; '.join(problems)} | "
                  f"0-{stop:g} s, h={step:g} | {result['rows']} x {result['columns']} | {result['max_abs']:.3g} | "
                  f"{result['max_rel']:.3g} |")


if __name__ == "__main__":
    main()
