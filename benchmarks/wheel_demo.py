"""The demo from an installed wheel: build the sdist and the wheel of this checkout, install the
wheel into a fresh virtual environment, and run `fmubuilder demo` there, from a folder outside
the checkout and with an empty build cache (so the example FMUs are built from the package's
own copy of the sources).

    python benchmarks/wheel_demo.py [--workdir DIR] [--with-dependencies]

By default the environment sees the system's packages (torch, fmpy, ... as installed) and only
fmubuilder comes from the wheel; --with-dependencies installs them from the package index too.
Prints where fmubuilder was imported from, the demo's summary and its exit code.
"""
from __future__ import annotations

import argparse
import os
import pathlib
import shutil
import subprocess
import sys
import tempfile
import time

REPO = pathlib.Path(__file__).resolve().parents[1]
NOT_SHIPPED = shutil.ignore_patterns(".git", "build", "dist", "*.egg-info", "__pycache__", ".pytest_cache",
                                     "fmubuilder-demo", "*.fmu")


def user_env(**extra) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME")}
    env.update(extra)
    return env


def build_wheel(work: pathlib.Path) -> pathlib.Path:
    source = work / "source"
    shutil.copytree(REPO, source, ignore=NOT_SHIPPED)
    subprocess.run([sys.executable, "-m", "build", "--no-isolation", "--outdir", str(work / "dist"), str(source)],
                   check=True, capture_output=True, env=user_env())
    return next((work / "dist").glob("fmubuilder-*.whl"))


def install(wheel: pathlib.Path, venv: pathlib.Path, with_dependencies: bool) -> pathlib.Path:
    options = [] if with_dependencies else ["--system-site-packages"]
    subprocess.run([sys.executable, "-m", "venv", *options, str(venv)], check=True)
    pip = [str(venv / "bin" / "python"), "-m", "pip", "install", "--quiet"]
    pip += [str(wheel)] if with_dependencies else ["--no-deps", "--no-index", "--ignore-installed", str(wheel)]
    subprocess.run(pip, check=True, env=user_env())
    return venv / "bin"


def main() -> int:
    parser = argparse.ArgumentParser(description="fmubuilder demo from the wheel of this checkout, in a fresh venv")
    parser.add_argument("--workdir", type=pathlib.Path, help="keep everything here (default: a temporary folder)")
    parser.add_argument("--with-dependencies", action="store_true", help="install the dependencies into the venv too")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="fmubuilder-wheel-") as scratch:
        work = args.workdir or pathlib.Path(scratch)
        work.mkdir(parents=True, exist_ok=True)
        wheel = build_wheel(work)
        print(f"wheel: {wheel.name} ({wheel.stat().st_size / 1e6:.1f} MB)")
        bin_dir = install(wheel, work / "venv", args.with_dependencies)
        run_dir = work / "run"
        run_dir.mkdir(exist_ok=True)
        env = user_env(FMUBUILDER_CACHE=str(work / "cache"))
        where = subprocess.run([str(bin_dir / "python"), "-c", "import fmubuilder; print(fmubuilder.__file__)"],
                               cwd=run_dir, env=env, capture_output=True, text=True, check=True).stdout.strip()
        print(f"fmubuilder imported from {where}")
        started = time.monotonic()
        demo = subprocess.run([str(bin_dir / "fmubuilder"), "demo", "--force"], cwd=run_dir, env=env,
                              capture_output=True, text=True)
        summary = [line for line in demo.stdout.splitlines() if not line.startswith("training")]
        print("\n".join(summary[-16:]))
        if demo.returncode != 0:
            print(demo.stderr[-2000:], file=sys.stderr)
        print(f"fmubuilder demo: exit code {demo.returncode}, {time.monotonic() - started:.0f} s wall clock")
        return demo.returncode


if __name__ == "__main__":
    sys.exit(main())
