"""Fail when a test run skipped a test that tests/expected_skips.toml does not allow.

    python tools/check_skips.py out/skips/bpy5.0.1.json [more reports]

Each report is written by ``pytest --skip-report=PATH`` (tests/skip_report.py) and is named
``bpy<version>.json`` after the Blender it ran under (``make test-built`` does this). A skip
is allowed when an entry of tests/expected_skips.toml names that Blender, the test and the
reason, and (for entries with ``outside_ci_only = true``) the run was not under CI.
Exit status: 0 every skip allowed, 1 an unexpected skip (each listed with where it came
from), 2 a report or the list itself is unreadable. Expected skips that did not happen are
printed as notes only (not those allowed on developers' machines only): runs are narrowed
per Blender (see the Makefile's test-others), so a missing one is no error.
"""
import argparse
import json
import re
import sys
import tomllib
from dataclasses import dataclass
from pathlib import Path

EXPECTED = Path(__file__).resolve().parents[1] / "tests" / "expected_skips.toml"
REPORT_NAME = re.compile(r"^bpy(?P<version>\d+\.\d+\.\d+)\.json$")
FIELDS = {"blender", "test", "reason", "why", "outside_ci_only"}


@dataclass(frozen=True)
class AllowedSkip:
    """One entry of tests/expected_skips.toml."""
    blender: tuple[str, ...]  # version patterns: "4.2.*", "*"
    test: str                 # test id pattern: "tests/blender/test_volume_bake.py::*"
    reason: str               # text the skip's reason must contain
    why: str                  # why this skip is acceptable (for the reader; required)
    outside_ci_only: bool = False  # allowed on a developer's machine, never under CI

    def allows(self, version: str, nodeid: str, reason: str, ci: bool) -> bool:
        return ((not (ci and self.outside_ci_only))
                and any(_wildcard(p).fullmatch(version) for p in self.blender)
                and _wildcard(self.test).fullmatch(nodeid) is not None
                and self.reason in reason)


def _wildcard(pattern: str) -> re.Pattern:
    """``*`` matches any text; every other character stands for itself (test ids hold
    ``[`` and ``.``, which fnmatch or a regular expression would read as syntax)."""
    return re.compile(".*".join(re.escape(part) for part in pattern.split("*")), re.S)


class ListError(ValueError):
    """tests/expected_skips.toml or a report cannot be read as documented."""


def load_expected(path: Path = EXPECTED) -> list[AllowedSkip]:
    try:
        entries = tomllib.loads(path.read_text(encoding="utf-8")).get("skip", [])
    except (OSError, tomllib.TOMLDecodeError) as error:
        raise ListError(f"{path}: {error}") from None
    allowed = []
    for number, entry in enumerate(entries, 1):
        where = f"{path.name}, [[skip]] #{number}"
        unknown = set(entry) - FIELDS
        if unknown:
            raise ListError(f"{where}: unknown field(s) {sorted(unknown)}; the fields are {sorted(FIELDS)}")
        for field in ("blender", "test", "reason", "why"):
            if not entry.get(field):
                raise ListError(f"{where}: '{field}' is required and must not be empty")
        blender = entry["blender"]
        blender = (blender,) if isinstance(blender, str) else tuple(blender)
        if not all(isinstance(b, str) for b in blender) or not all(
                isinstance(entry[f], str) for f in ("test", "reason", "why")):
            raise ListError(f"{where}: 'blender' is a text or a list of texts; 'test', 'reason', 'why' are texts")
        allowed.append(AllowedSkip(blender, entry["test"], entry["reason"], entry["why"],
                                   bool(entry.get("outside_ci_only", False))))
    return allowed


def read_report(path: Path) -> tuple[str, dict]:
    """(Blender version, report) of ``bpy<version>.json``."""
    match = REPORT_NAME.match(path.name)
    if not match:
        raise ListError(f"{path}: a skip report is named bpy<version>.json after the Blender it ran under")
    try:
        report = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as error:
        raise ListError(f"{path}: no readable skip report ({error}); did pytest run with --skip-report?") from None
    version = match["version"]
    if report.get("bpy") not in (None, version):
        raise ListError(f"{path}: named for Blender {version} but the tests ran under bpy {report['bpy']}")
    return version, report


def check(reports: list[Path], allowed: list[AllowedSkip]) -> tuple[list[str], list[str]]:
    """(unexpected skips, notes on entries no report used), each as a line to print."""
    unexpected, used, versions = [], set(), []
    for path in reports:
        version, report = read_report(path)
        versions.append(version)
        for skip in report["skips"]:
            matches = [i for i, a in enumerate(allowed)
                       if a.allows(version, skip["nodeid"], skip["reason"], report["ci"])]
            used.update(matches)
            if not matches:
                unexpected.append(f"bpy {version}: {skip['nodeid']}\n    reason: {skip['reason']}"
                                  + (f"\n    from:   {skip['location']}" if skip.get("location") else ""))
    unused = [f"{a.test} on {', '.join(a.blender)} ({a.reason!r})"
              for i, a in enumerate(allowed)
              if i not in used and not a.outside_ci_only
              and any(_wildcard(p).fullmatch(v) for p in a.blender for v in versions)]
    return unexpected, unused


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("reports", nargs="+", type=Path, help="bpy<version>.json from pytest --skip-report")
    parser.add_argument("--expected", type=Path, default=EXPECTED, help="the allowed skips (default: %(default)s)")
    args = parser.parse_args(argv)
    try:
        allowed = load_expected(args.expected)
        unexpected, unused = check(args.reports, allowed)
        skipped = sum(len(read_report(p)[1]["skips"]) for p in args.reports)
    except ListError as error:
        print(f"check_skips: error: {error}", file=sys.stderr)
        return 2
    names = ", ".join(p.name for p in args.reports)
    if unexpected:
        print(f"check_skips: {len(unexpected)} skip(s) that {args.expected.name} does not allow ({names}):",
              file=sys.stderr)
        for line in unexpected:
            print("  " + line, file=sys.stderr)
        print(f"Fix the cause, or, if the skip is right, add an entry to {args.expected} "
              "(blender, test, reason, why).", file=sys.stderr)
        return 1
    print(f"check_skips: {skipped} skip(s) in {names}, each allowed by {args.expected.name}")
    for line in unused:
        print(f"  note: no skip of {line} in these runs")
    return 0


if __name__ == "__main__":
    sys.exit(main())
