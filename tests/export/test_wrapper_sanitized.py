"""The static C wrapper on its own: it compiles cleanly against a hand-written configuration,
and it runs under AddressSanitizer and UndefinedBehaviorSanitizer (with leak detection) with the
same results as the production build.

The sanitizer runtimes refuse dlopen(RTLD_DEEPBIND), so the sanitized builds define
HYBRID_SANITIZER_BUILD (the original is loaded without it) and the host loads the wrapper with
RTLD_LOCAL (FMU_HOST_RTLD_LOCAL), under which the original's own calls still reach itself.
"""
from __future__ import annotations

import os
import shutil
import subprocess
import zipfile
from pathlib import Path

import pytest

from fmubuilder.build import example_fmu
from fmubuilder.fmi import read_model_info

from .test_wrapper import FMI_HEADERS, extracted, make_hybrid

HERE = Path(__file__).resolve().parent
TEMPLATES = HERE.parents[1] / "c_templates"
SAMPLE_CONFIG = HERE / "host" / "sample_config"
SAMPLE_GUID = "{sample-hybrid-of-the-bouncing-ball}"
SANITIZE = ["-fsanitize=address,undefined", "-fno-sanitize-recover=all", "-fno-omit-frame-pointer"]
WARNINGS = ["-Wall", "-Wextra", "-Wno-type-limits", "-Werror"]
SANITIZER_ENV = {"ASAN_OPTIONS": "detect_leaks=1:abort_on_error=0:exitcode=97",
                 "UBSAN_OPTIONS": "print_stacktrace=1:halt_on_error=1:exitcode=98",
                 "FMU_HOST_RTLD_LOCAL": "1"}

pytestmark = pytest.mark.skipif(shutil.which("cc") is None, reason="no C compiler")


def compile_library(sources, include_dirs, output: Path, *flags) -> Path:
    command = ["cc", "-std=c99", "-g", "-O1", "-fPIC", "-shared", "-ffp-contract=off", "-Wl,-Bsymbolic", *flags,
               *[f"-I{d}" for d in include_dirs], f"-I{FMI_HEADERS}", *map(str, sources), "-o", str(output),
               "-ldl", "-lpthread", "-lm"]
    result = subprocess.run(command, capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    return output


def compile_host(output: Path, source: Path, *flags) -> Path:
    command = ["cc", "-g", "-O1", *flags, f"-I{FMI_HEADERS}", str(source), "-o", str(output), "-ldl", "-lpthread"]
    result = subprocess.run(command, capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    return output


def run(command, sanitized: bool, **env) -> subprocess.CompletedProcess:
    environment = {**os.environ, "FMU_HOST_FMU_STATE": "1", **env, **(SANITIZER_ENV if sanitized else {})}
    result = subprocess.run([str(c) for c in command], capture_output=True, text=True, timeout=300, env=environment)
    assert "Sanitizer" not in result.stderr and "runtime error" not in result.stderr, result.stderr[-4000:]
    assert result.returncode == 0, result.stderr[-4000:]
    return result


@pytest.fixture(scope="module")
def hosts(tmp_path_factory):
    folder = tmp_path_factory.mktemp("hosts")
    source = HERE / "host" / "fmu_host.c"
    return {"plain": compile_host(folder / "fmu_host", source),
            "sanitized": compile_host(folder / "fmu_host_asan", source, *SANITIZE)}


@pytest.fixture(scope="module")
def sample_resources(tmp_path_factory):
    """A resources folder holding the bouncing ball's binary, as the sample configuration expects."""
    resources = tmp_path_factory.mktemp("sample") / "resources"
    resources.mkdir()
    with zipfile.ZipFile(example_fmu("bouncing_ball")) as original:
        (resources / "bouncing_ball.so").write_bytes(original.read("binaries/linux64/bouncing_ball.so"))
    return resources


def test_static_wrapper_compiles_on_its_own_without_warnings(tmp_path):
    for flags in ([], ["-DHYBRID_SANITIZER_BUILD", *SANITIZE]):
        compile_library([TEMPLATES / "hybrid_wrapper.c"], [SAMPLE_CONFIG, TEMPLATES], tmp_path / "sample.so",
                        *WARNINGS, *flags)


# A <dlfcn.h> as a C library without RTLD_DEEPBIND (musl, macOS) declares it.
DLFCN_WITHOUT_DEEPBIND = """
#define RTLD_LAZY 1
#define RTLD_NOW 2
#define RTLD_LOCAL 0
#define RTLD_GLOBAL 256
typedef struct { const char *dli_fname; void *dli_fbase; const char *dli_sname; void *dli_saddr; } Dl_info;
void *dlopen(const char *, int);
void *dlsym(void *, const char *);
int dlclose(void *);
char *dlerror(void);
int dladdr(const void *, Dl_info *);
"""


def test_static_wrapper_refuses_a_c_library_without_rtld_deepbind(tmp_path):
    (tmp_path / "dlfcn.h").write_text(DLFCN_WITHOUT_DEEPBIND)
    command = ["cc", "-std=c99", "-fsyntax-only", f"-I{tmp_path}", f"-I{SAMPLE_CONFIG}", f"-I{TEMPLATES}",
               f"-I{FMI_HEADERS}", str(TEMPLATES / "hybrid_wrapper.c")]
    result = subprocess.run(command, capture_output=True, text=True)
    assert result.returncode != 0
    errors = [line for line in result.stderr.splitlines() if ": error:" in line]
    assert len(errors) == 1 and "needs dlopen with RTLD_DEEPBIND" in errors[0], result.stderr
    # The sanitizer build does without it, so the same header compiles there.
    result = subprocess.run(command + ["-DHYBRID_SANITIZER_BUILD"], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr


def sample_run(host, library, resources, sanitized):
    """Final states and Real values of the sample hybrid after 3 cycles of 400 Euler steps."""
    vrs = ["0", "2", "3", "10"]   # h, v, der(v) corrected, the network output
    result = run([host, library, SAMPLE_GUID, resources.as_uri(), 2, 1, 3, 400, 0.01, *vrs], sanitized)
    return [float(v) for v in result.stdout.split()]


def test_sample_wrapper_under_sanitizers_matches_the_production_build(hosts, sample_resources, tmp_path):
    plain = compile_library([TEMPLATES / "hybrid_wrapper.c"], [SAMPLE_CONFIG, TEMPLATES], tmp_path / "plain.so")
    sanitized = compile_library([TEMPLATES / "hybrid_wrapper.c"], [SAMPLE_CONFIG, TEMPLATES], tmp_path / "asan.so",
                                "-DHYBRID_SANITIZER_BUILD", *SANITIZE)
    expected = sample_run(hosts["plain"], plain, sample_resources, sanitized=False)
    assert sample_run(hosts["sanitized"], sanitized, sample_resources, sanitized=True) == expected
    # The network acts: der(v) = -g + 0.1 h - 0.2 v + 0.01 * (-g), with the ball's g = 9.81.
    h, v, der_v, ann = expected[2:]
    assert ann == pytest.approx(0.1 * h - 0.2 * v + 0.01 * -9.81, rel=1e-12)
    assert der_v == pytest.approx(-9.81 + ann, rel=1e-12)


def sanitized_build_of(fmu: Path, folder: Path) -> tuple[Path, str]:
    """The FMU extracted to `folder` with its binary rebuilt from its own sources/ under the sanitizers."""
    library, resources = extracted(fmu, folder)
    sources = sorted((folder / "sources").glob("*.c"))
    compile_library(sources, [folder / "sources"], library, "-DHYBRID_SANITIZER_BUILD", *SANITIZE)
    return library, resources


def test_exported_sources_under_sanitizers_match_the_exported_binary(hosts, tmp_path):
    spec, fmu = make_hybrid(tmp_path / "ball", example_fmu("bouncing_ball"), ["der(v)"], ["h", "v", "der(v)"],
                            seed=1)
    info = read_model_info(fmu)
    ann = str(info.variable("hybrid.v.ann").value_reference)
    der_v = str(info.variable("der(v)").value_reference)
    library, resources = extracted(fmu, tmp_path / "plain")
    arguments = [info.guid, resources, 2, 1, 3, 400, 0.01, der_v, ann]
    expected = run([hosts["plain"], library, *arguments], sanitized=False).stdout
    library, resources = sanitized_build_of(fmu, tmp_path / "sanitized")
    arguments[1] = resources
    assert run([hosts["sanitized"], library, *arguments], sanitized=True).stdout == expected


# -- the exported FMU under attack ------------------------------------------------------------------

@pytest.fixture(scope="module")
def attacked_ball(tmp_path_factory):
    folder = tmp_path_factory.mktemp("attacked")
    spec, fmu = make_hybrid(folder / "ball", example_fmu("bouncing_ball"), ["der(v)"], ["h", "v", "der(v)"], seed=5)
    info = read_model_info(fmu)
    arguments = [info.guid, info.n_states, info.n_event_indicators, info.variable("h").value_reference,
                 info.variable("g").value_reference, info.variable("hybrid.v.p_ann").value_reference]
    assert info.variable("g").variability == "fixed"
    return fmu, arguments


@pytest.mark.parametrize("sanitized", [False, True], ids=["production", "sanitized"])
def test_exported_fmu_under_attack(attacked_ball, sanitized, tmp_path):
    """Wrong-state calls, bad arguments, forged FMU states, double free, 20 instances, 2 threads."""
    fmu, (guid, *sizes_and_vrs) = attacked_ball
    flags = SANITIZE if sanitized else []
    attack = compile_host(tmp_path / "fmu_attack", HERE / "host" / "fmu_attack.c", *flags)
    if sanitized:
        library, resources = sanitized_build_of(fmu, tmp_path / "fmu")
    else:
        library, resources = extracted(fmu, tmp_path / "fmu")
    result = run([attack, library, guid, resources, *sizes_and_vrs], sanitized)
    assert result.stdout.startswith("passed ") and int(result.stdout.split()[1]) > 500, result.stdout
