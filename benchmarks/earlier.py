"""A module of the project as it was at an earlier commit, for A/B benchmarks that time the
earlier and the current code in one process (this VM's speed drifts by 15% within minutes,
so separate runs cannot be compared)."""
import importlib.util
import os
import subprocess
import tempfile

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def earlier_module(sha: str, path: str, name: str):
    """The module at ``path`` (relative to the repository, under core/) as it was at ``sha``,
    imported from a temporary file as ``name``; its relative imports are made absolute
    (``core.…``), so the checkout's ``core`` must be importable."""
    source = subprocess.run(["git", "show", f"{sha}:{path}"], cwd=ROOT, check=True, capture_output=True,
                            text=True).stdout
    package = os.path.dirname(path).replace("/", ".")
    parent = package.rsplit(".", 1)[0]
    source = source.replace("from .. import", f"from {parent} import").replace("from ..", f"from {parent}.")
    source = source.replace("from . import", f"from {package} import").replace("from .", f"from {package}.")
    folder = tempfile.mkdtemp(prefix="visibake-ab-")
    file = os.path.join(folder, f"{name}.py")
    with open(file, "w") as handle:
        handle.write(source)
    spec = importlib.util.spec_from_file_location(name, file)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module
