"""Scale-out on a render farm (issue 20): a bake run as steps that exchange files in a job
folder (core.distributed.farm), the driver replayed once per step and each row range answered
by a part command, equals the one-process bake bit for bit; and the folder's guards."""
import json
import os

import pytest
from test_split_bake import PASSES, _assert_same_images, _interior, _open_ground

from core.distributed import farm
from core.errors import BakeRefused
from core.pipeline.relight import bake
from core.settings import BakeSettings


def run_farm(folder, scene, settings, parts):
    """Step, parts, step, ... as the Flamenco job type orders them; returns (result, steps)."""
    steps = 0
    while True:
        steps += 1
        try:
            result = bake(scene, settings, split=farm.FarmRows(folder, parts))
        except farm.PartsPending as pending:
            assert farm.read_pending(str(folder)) == {"call": pending.call}
            for index in range(parts):
                farm.run_part(str(folder), index)
            # A part the job does not have (a job type submitted with other --parts) is refused.
            with pytest.raises(BakeRefused, match=f"--part {parts}: the farm job in .* has parts 0 to {parts - 1}"):
                farm.run_part(str(folder), parts)
            continue
        farm.mark_done(str(folder))
        return result, steps


@pytest.mark.parametrize("scene, shadows, parts", [("interior", "exact", 3), ("interior", "fractions", 2),
                                                    ("open", "exact", 4)])
def test_a_bake_in_farm_steps_equals_the_one_process_bake(tmp_path, scene, shadows, parts):
    built = _interior() if scene == "interior" else _open_ground()
    settings = BakeSettings(directions=32, bounces=2, interleave=2 if scene == "interior" else 3,
                            footprint_samples=4, seed=3, shadows=shadows, passes=PASSES, emitter_samples=16)
    farm.write_job_package(str(tmp_path), built, settings)
    result, steps = run_farm(tmp_path, built, settings, parts)
    _assert_same_images(result, bake(built, settings))
    # One step per executor call, and the last; within what the job type plans.
    calls = len(os.listdir(tmp_path / "calls"))
    assert steps == calls + 1
    world_rotations = 9 if scene == "open" else 1
    assert steps <= farm.estimated_steps(settings, len(built.lights), world_rotations)
    assert farm.read_pending(str(tmp_path)) == {"done": True}
    assert farm.run_part(str(tmp_path), 0) == "nothing to do: the bake is finished"
    assert len(os.listdir(tmp_path / "rows")) == parts


def test_a_part_run_again_and_a_folder_of_another_bake(tmp_path):
    scene = _interior()
    settings = BakeSettings(directions=16, bounces=1, interleave=2, footprint_samples=4)
    farm.write_job_package(str(tmp_path), scene, settings)
    assert "not asked for anything" in farm.run_part(str(tmp_path), 0)
    with pytest.raises(farm.PartsPending):
        bake(scene, settings, split=farm.FarmRows(tmp_path, 2))
    assert "rows 0 to" in farm.run_part(str(tmp_path), 0)
    assert "already answered" in farm.run_part(str(tmp_path), 0)  # a retried task changes nothing
    farm.run_part(str(tmp_path), 1)
    with pytest.raises(BakeRefused, match="holds another bake"):
        farm.write_job_package(str(tmp_path), scene, BakeSettings(directions=32, bounces=1))
    (tmp_path / "pending.json").write_text("[1]")
    with pytest.raises(BakeRefused, match="damaged"):
        farm.run_part(str(tmp_path), 0)
    (tmp_path / "pending.json").write_text(json.dumps({"call": 0}))
    part = tmp_path / "calls" / "0000" / "part-0000.vbv"
    data = bytearray(part.read_bytes())
    data[len(data) // 2] ^= 0xFF
    part.write_bytes(bytes(data))
    with pytest.raises(BakeRefused, match="damaged|changed"):
        bake(scene, settings, split=farm.FarmRows(tmp_path, 2))


@pytest.mark.parametrize("call, said", [
    ({"task": "np", "parts": 2, "ranges": [[0, 4], [4, 8]], "per_range": [[], []], "shared": []}, "unknown task 'np'"),
    ({"task": "table_stats", "parts": 1, "ranges": [[0, 4], [4, 8]], "per_range": [[], []], "shared": []},
     "does not hold 1 parts' ranges"),
    ({"task": "table_stats", "parts": 2, "ranges": 7, "per_range": [[], []], "shared": []}, "ranges of rows"),
    ({"task": "table_stats", "parts": 2, "ranges": [[0, 4], [4, 8]], "per_range": [[]], "shared": []},
     "ranges of rows"),
    ({"task": "table_stats", "ranges": [[0, 4]], "per_range": [[]], "shared": []}, "lacks parts"),
])
def test_a_call_file_of_another_shape_is_refused_naming_it(tmp_path, call, said):
    from core.distributed.package import write_values

    (tmp_path / "calls" / "0000").mkdir(parents=True)
    write_values(tmp_path / "calls" / "0000" / "call.vbv", call)
    (tmp_path / "pending.json").write_text(json.dumps({"call": 0}))
    with pytest.raises(BakeRefused, match=f"{tmp_path / 'calls' / '0000' / 'call.vbv'}.*{said}"):
        farm.run_part(str(tmp_path), 0)
