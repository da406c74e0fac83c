"""benchmarks/objects.py: its pooling of psimap eval's object rows (no training), so the benchmark's
table says what the issue's targets mean: missed things count 0, furniture is not among the movable."""

import pytest
from scripts import load_script

B = load_script("benchmarks/objects.py", "bench_objects")


def _obj(i, name, found, f1, f25, role, static_class=False, mass=None, gt_mass=None):
    err = None if mass is None or gt_mass is None else (mass - gt_mass) / gt_mass
    return {"id": i, "name": name, "class": name, "size_m": 0.1 * i, "found": found, "fscore_10mm": f1,
            "fscore_25mm": f25, "role": role, "static_class": static_class, "reason": "" if role == "dynamic" else "why",
            "prediction": f"{name}_{i}" if found else None, "mass_kg": mass, "gt_mass_kg": gt_mass,
            "mass_error": err, "observed_completeness_10mm": 0.9}


def _row(size, seed, objs):
    return {"size": size, "seed": seed, "objects": {"per_object": objs, "summary": {"n_false_objects": 1}},
            "geometry": {"f1": 0.9, "chamfer_l1": 0.01}, "panoptic": {"pq": 0.8}, "train_wall_s": 10.0,
            "train_cpu_s": 8.0, "export_wall_s": 5.0, "export_cpu_s": 4.0, "surfels": 1000,
            "surfels_on_things": 100, "surfels_of": {}}


def test_summary_pools_things_counts_missed_as_zero_and_leaves_furniture_out():
    rows = [_row("320x240", 0, [_obj(1, "table", True, 0.4, 0.6, "static", static_class=True),
                                _obj(2, "ball", True, 1.0, 1.0, "dynamic", mass=0.3, gt_mass=0.2),
                                _obj(3, "box", True, 0.8, 1.0, "static")]),
            _row("320x240", 1, [_obj(4, "mug", False, 0.0, 0.0, "n/a"),
                                _obj(5, "bottle", True, 0.6, 0.9, "dynamic", mass=0.9, gt_mass=1.0)])]
    s = B.summarize(rows)
    assert s["things"] == 5 and s["found"] == pytest.approx(0.8)
    assert s["movable"] == 3 and s["dynamic"] == pytest.approx(2 / 3)      # the table is not movable
    assert s["f1cm"] == pytest.approx((0.4 + 1.0 + 0.8 + 0.0 + 0.6) / 5)   # the missed mug counts 0
    assert s["f1cm_things"] == pytest.approx((1.0 + 0.8 + 0.0 + 0.6) / 4)
    assert s["mass_error"] == pytest.approx(0.3) and s["n_mass"] == 2       # median of 50 % and 10 %
    assert s["false_objects"] == 2
    text, headlines = B.tables(rows + [_row("160x120", 0, [_obj(1, "ball", True, 0.5, 0.9, "dynamic")])])
    summary_table = text.split("Per object:")[0]
    lines = [ln for ln in summary_table.splitlines() if ln.startswith("| 160x120 |") or ln.startswith("| 320x240 |")]
    assert [ln.split("|")[1].strip() for ln in lines] == ["160x120", "320x240"]     # by image size
    assert "| 0,1 | 5 | 80 % | 67 % of 3 |" in lines[1]
    assert headlines[0] == ("found / dynamic, 320x240", "80 % / 67 %")
