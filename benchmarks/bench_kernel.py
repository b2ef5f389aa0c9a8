"""Per-call cost of the generated C kernel versus onnxruntime on the same ONNX network.

For each network the kernel is timed three ways, all in this run:
  C loop   a small C program calls <prefix>_run in a loop (no Python in the measurement)
  cffi     the kernel in a shared library called from Python through cffi (ABI mode)
  ORT      onnxruntime InferenceSession.run from Python, single-threaded (baseline)
Each figure is the best of several repeats, in nanoseconds per call.

    python benchmarks/bench_kernel.py [--calls N] [--repeats R]
"""

from __future__ import annotations

import argparse
import subprocess
import tempfile
import timeit
from pathlib import Path

import cffi
import numpy as np
import onnxruntime
import torch

from fmubuilder.export import freeze, generate_kernel

CFLAGS = ["-std=c99", "-O2"]

NETWORKS = {
    "2-16-16-1 tanh": [2, 16, 16, 1],
    "4-32-32-2 tanh": [4, 32, 32, 2],
}

# The input changes every call so the compiler cannot hoist the call out of the loop; the
# kernel lives in its own translation unit, so it is not inlined either.
HARNESS = r"""
#define _POSIX_C_SOURCE 199309L /* clock_gettime under -std=c99 */
#include <stdio.h>
#include <stdlib.h>
#include <time.h>
#include "{prefix}.h"

static double seconds(void)
{{
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);
    return (double)t.tv_sec + 1e-9 * (double)t.tv_nsec;
}}

int main(int argc, char **argv)
{{
    long calls = atol(argv[1]);
    int repeats = atoi(argv[2]);
    double input[{prefix}_N_INPUTS], output[{prefix}_N_OUTPUTS], checksum = 0.0, best = 1e300;
    for (int i = 0; i < {prefix}_N_INPUTS; ++i) {{
        input[i] = 0.1 * (i + 1);
    }}
    for (int r = 0; r < repeats; ++r) {{
        double start = seconds();
        for (long n = 0; n < calls; ++n) {{
            input[0] = 1e-3 * (double)(n & 1023);
            {prefix}_run(input, output);
            checksum += output[0];
        }}
        double elapsed = seconds() - start;
        best = elapsed < best ? elapsed : best;
    }}
    printf("%.6f %.17g\n", 1e9 * best / (double)calls, checksum);
    return 0;
}}
"""


def mlp(widths: list[int], seed: int = 0) -> torch.nn.Module:
    torch.manual_seed(seed)
    layers: list[torch.nn.Module] = []
    for n_in, n_out in zip(widths[:-1], widths[1:]):
        layers += [torch.nn.Linear(n_in, n_out), torch.nn.Tanh()]
    return torch.nn.Sequential(*layers[:-1])  # linear output layer


def build(kernel, directory: Path) -> tuple[Path, Path]:
    """Compile the timing program and a shared library from the kernel source."""
    _, source = kernel.write(directory)
    harness = directory / "harness.c"
    harness.write_text(HARNESS.format(prefix=kernel.prefix))
    program, library = directory / "harness", directory / f"lib{kernel.prefix}.so"
    subprocess.run(["gcc", *CFLAGS, "-o", str(program), str(harness), str(source), "-lm"], check=True)
    subprocess.run(["gcc", *CFLAGS, "-shared", "-fPIC", "-o", str(library), str(source), "-lm"], check=True)
    return program, library


def time_c_loop(program: Path, calls: int, repeats: int) -> float:
    out = subprocess.run([str(program), str(calls), str(repeats)], check=True, capture_output=True, text=True)
    return float(out.stdout.split()[0])


def best_ns(function, calls: int, repeats: int) -> float:
    function()  # warm up
    return 1e9 * min(timeit.repeat(function, number=calls, repeat=repeats)) / calls


def bench_network(name: str, widths: list[int], directory: Path, calls: int, repeats: int) -> dict:
    frozen = freeze(mlp(widths), widths[0], directory / "net.onnx")
    kernel = generate_kernel(frozen.path, prefix="bench")
    program, library = build(kernel, directory)

    ffi = cffi.FFI()
    ffi.cdef("void bench_run(const double *input, double *output);")
    lib = ffi.dlopen(str(library))
    x = np.linspace(0.1, 0.5, widths[0]).reshape(1, -1)
    c_in, c_out = ffi.new("double[]", x.ravel().tolist()), ffi.new(f"double[{kernel.n_outputs}]")

    options = onnxruntime.SessionOptions()
    options.intra_op_num_threads = 1
    options.inter_op_num_threads = 1
    session = onnxruntime.InferenceSession(str(frozen.path), options, providers=["CPUExecutionProvider"])
    feeds = {"input": x}

    # Same network, same numbers: guard against timing something else.
    lib.bench_run(c_in, c_out)
    np.testing.assert_allclose(list(c_out), session.run(None, feeds)[0].ravel(), rtol=1e-12, atol=1e-13)

    return {
        "network": name,
        "c_loop": time_c_loop(program, calls, repeats),
        "cffi": best_ns(lambda: lib.bench_run(c_in, c_out), calls // 10, repeats),
        "ort": best_ns(lambda: session.run(None, feeds), calls // 100, repeats),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--calls", type=int, default=2_000_000, help="calls per repeat of the C loop")
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()

    print(f"onnxruntime {onnxruntime.__version__}, torch {torch.__version__}, gcc {' '.join(CFLAGS)}")
    header = f"{'network':<18}{'C loop ns':>11}{'cffi ns':>10}{'ORT ns':>10}{'ORT/C loop':>12}{'ORT/cffi':>10}"
    print(header)
    print("-" * len(header), flush=True)
    for name, widths in NETWORKS.items():
        with tempfile.TemporaryDirectory() as tmp:
            r = bench_network(name, widths, Path(tmp), args.calls, args.repeats)
        print(
            f"{r['network']:<18}{r['c_loop']:>11.1f}{r['cffi']:>10.1f}{r['ort']:>10.1f}"
            f"{r['ort'] / r['c_loop']:>11.0f}x{r['ort'] / r['cffi']:>9.1f}x"
        )


if __name__ == "__main__":
    main()
