"""Build hook: the package carries the C templates, CMake files and example sources.

They live at the top of the source tree (their one copy); building the package copies them
into fmubuilder/_data, where fmubuilder.build.repo_root() finds them once installed. The rest
of the configuration is in pyproject.toml.
"""
import pathlib
import shutil

from setuptools import setup
from setuptools.command.build_py import build_py

ROOT = pathlib.Path(__file__).resolve().parent
# Keep in step with fmubuilder.build.DATA_ITEMS.
DATA_ITEMS = ("CMakeLists.txt", "cmake", "c_templates", "examples")
SKIPPED = shutil.ignore_patterns(".*", "__pycache__", "*.pyc")


class BuildPyWithData(build_py):
    def run(self):
        super().run()
        if self.editable_mode:  # an editable install reads the source tree itself
            return
        target = pathlib.Path(self.build_lib) / "fmubuilder" / "_data"
        shutil.rmtree(target, ignore_errors=True)
        target.mkdir(parents=True)
        for item in DATA_ITEMS:
            source = ROOT / item
            if source.is_dir():
                shutil.copytree(source, target / item, ignore=SKIPPED)
            else:
                shutil.copy2(source, target / item)


setup(cmdclass={"build_py": BuildPyWithData})
