"""User names as path components and datablock names (core.outputs.names)."""
import os
import unicodedata

import pytest

from core.errors import OutputRefused
from core.outputs.names import (
    MAX_COMPONENT_BYTES,
    component_key,
    datablock_name,
    image_name,
    inside_folder,
    path_component,
    unique_components,
)

NFC_E, NFD_E = unicodedata.normalize("NFC", "é"), unicodedata.normalize("NFD", "é")
HOSTILE = ["a/b", "a_b", "a:b", "A_B", "..", ".", "x/../../../../ESCAPED", "CON", "nul.txt", "Com1.exr", "trailing.",
           "trailing ", "", " ", "<>:\"|?*", "tab\tname", "\x00nul", NFC_E, NFD_E, "🙂 emoji", "x" * 70, "é" * 70,
           "lpt¹", "CONIN$", "back\\slash", ".hidden"]
WINDOWS_INVALID = set('<>:"/\\|?*') | {chr(c) for c in range(32)}
RESERVED = ({"CON", "PRN", "AUX", "NUL", "CONIN$", "CONOUT$"}
            | {f"{b}{d}" for b in ("COM", "LPT") for d in "0123456789¹²³"})


@pytest.mark.parametrize("name", HOSTILE)
def test_every_component_is_one_safe_name_on_every_platform(name):
    component = path_component(name)
    assert component not in ("", ".", "..")
    assert not WINDOWS_INVALID & set(component)
    assert component[-1] not in ". " and component[0] not in ". "
    assert component.split(".")[0].upper() not in RESERVED
    assert len(component.encode("utf-8")) <= MAX_COMPONENT_BYTES
    assert unicodedata.is_normalized("NFC", component)
    assert os.path.basename(os.path.join("out", component)) == component
    assert path_component(name) == component  # stable


def test_names_that_need_no_change_keep_it_and_others_keep_a_hash_of_the_original():
    for name in ("Ground", "Cube.001", "lighting_Key", NFC_E, "🙂 emoji", "Ünïcödé name"):
        assert path_component(name) == name
    changed = path_component("a/b")
    assert changed.startswith("a_b-") and changed != path_component("a:b") != path_component("a_b")
    assert path_component(NFD_E) != NFC_E and path_component(NFD_E).startswith(NFC_E + "-")
    assert path_component("CON").startswith("CON_") and path_component("nul.txt").startswith("nul_.txt")


def test_long_names_are_capped_with_distinct_hashes_at_a_character_boundary():
    long_a, long_b = "é" * 70 + "a", "é" * 70 + "b"
    a, b = path_component(long_a), path_component(long_b)
    assert a != b and len(a.encode()) <= MAX_COMPONENT_BYTES and len(b.encode()) <= MAX_COMPONENT_BYTES
    a.encode("utf-8")  # no cut character
    assert path_component("x" * 90, max_bytes=40) != path_component("x" * 91, max_bytes=40)


def test_unique_components_never_share_a_path_case_or_normalisation_insensitively():
    names = ["a/b", "a_b", "a:b", "A_B", NFC_E, NFD_E, "Box", "box", "x" * 120, "x" * 121, "report.json"]
    components = unique_components(names, reserved=["report.json"], suffix=".exr")
    assert set(components) == set(names)
    keys = [component_key(c + ".exr") for c in components.values()]
    assert len(set(keys)) == len(names)
    assert components["report.json"] == "report.json"  # report.json.exr takes no one's place
    folders = unique_components(names, reserved=["report.json", "visibake_cache"])
    assert component_key(folders["report.json"]) != component_key("report.json")
    # Independent of order, and of which other names are present for names that had to change.
    assert unique_components(list(reversed(names)), reserved=["report.json"], suffix=".exr") == components
    assert unique_components(["a/b"])["a/b"] == components["a/b"]
    assert unique_components(["Ground"]) == {"Ground": "Ground"}


def test_a_user_name_that_looks_hashed_does_not_take_a_cleaned_names_place():
    lookalike = path_component("a/b")
    components = unique_components(["a/b", lookalike])
    assert components["a/b"] != components[lookalike]


def test_inside_folder_refuses_paths_that_leave_the_folder(tmp_path):
    out = tmp_path / "a" / "b" / "out"
    out.mkdir(parents=True)
    assert inside_folder(str(out), "Ground", "lighting.exr") == os.path.join(str(out), "Ground", "lighting.exr")
    for components in (("..", "ESCAPED.exr"), ("x/../../../../ESCAPED.exr",), (str(tmp_path / "elsewhere"),), (".",)):
        with pytest.raises(OutputRefused, match="outside the output folder"):
            inside_folder(str(out), *components)
    (tmp_path / "elsewhere").mkdir()
    os.symlink(tmp_path / "elsewhere", out / "link")
    with pytest.raises(OutputRefused):
        inside_folder(str(out), "link", "lighting.exr")
    # A cleaned component stays inside whatever the name was.
    for name in HOSTILE:
        inside_folder(str(out), path_component(name), path_component(name) + ".exr")


def test_image_names_are_distinct_per_object_and_pass_and_never_cut():
    assert image_name("Ground", "lighting", 63) == "VB_Ground_lighting"
    assert image_name("Ground", "lighting_Key", 63) == "VB_Ground_lighting_Key"
    assert image_name("Ground_floor", "ao", 63) == "VB_Ground_floor_ao"
    clash = image_name("A", "lighting_direct", 63), image_name("A_lighting", "direct", 63)
    assert clash[0] != clash[1] and "VB_A_lighting_direct" not in clash
    long_names = {image_name("x" * 58 + suffix, "lighting", 63) for suffix in ("", "a", "b", "é")}
    assert len(long_names) == 4 and all(len(n.encode()) <= 63 for n in long_names)
    assert image_name("x" * 58, "lighting", 63) == image_name("x" * 58, "lighting", 63)
    # A plain name never equals the hashed name of another pair.
    hashed = image_name("A", "lighting_direct", 63)
    obj, pass_name = hashed[3:].rsplit("_", 1)
    assert image_name(obj, pass_name, 63) != hashed
    assert datablock_name("VisiBake Lighting ", ["é" * 40], 63).encode("utf-8")
    assert len(datablock_name("VisiBake Lighting ", ["é" * 40], 63).encode()) <= 63


def test_the_report_names_renamed_outputs_and_the_summary_counts_distinct_files():
    from core.outputs.names import renamed_warnings
    from core.outputs.report import Report
    from core.outputs.summary import summary_lines
    renamed = [{"name": "a/b", "kind": "object", "path": "/o/a_b-3ec69c85"},
               {"name": "a/b: lighting_x/+", "kind": "pass", "path": "/o/a_b-3ec69c85/lighting_x_+-c95d1e64.exr"}]
    settings = {"directions": 8, "bounces": 0, "shadows": "exact", "passes": ["lighting"]}
    files = ["/o/a_b-3ec69c85/lighting.exr", "/o/a_b-3ec69c85/lighting.exr", "/o/x/lighting.exr"]
    report = Report(settings=settings, files=files, renamed_outputs=renamed, warnings=renamed_warnings(renamed))
    again = Report.from_dict(report.to_dict())
    assert again.renamed_outputs == renamed and again.to_dict() == report.to_dict()
    lines = summary_lines(report)
    assert "  files: 2 written, 2 output name(s) changed" in lines
    assert any("object 'a/b' -> /o/a_b-3ec69c85" in line for line in lines)
    assert "renamed_outputs" not in Report().to_dict() and renamed_warnings([]) == []
