"""The mesh options' record (genre_backend/inference/options.py): checks, merge, schema, the CLI flags made from it."""

from __future__ import annotations

import argparse
import dataclasses
import math

import pytest
import torch

from genre_backend.config import GeometryConfig
from genre_backend.inference.options import (BY_NAME, DEFAULT_QUALITY, OPTIONS, QUALITIES, MeshOptions, OptionError,
                                             add_arguments, from_arguments, parse_request_options, schema)

DISTANCE = GeometryConfig(target="distance", default_threshold=0.45, hole_closing=1, pit_sealing=4, test_time_mirror=True)


def test_every_field_is_an_option_with_a_label_help_and_a_default_rule():
    assert [o.name for o in OPTIONS] == [f.name for f in dataclasses.fields(MeshOptions)]
    for o in OPTIONS:
        assert o.label and o.help and "\n" not in o.help and o.kind in ("float", "int", "bool", "choice")
        if o.kind in ("float", "int"):
            assert o.lo < o.hi
        if o.weights:  # the default comes from the weights' geometry: a field of GeometryConfig of the option's kind
            value = getattr(GeometryConfig(), o.weights)
            assert o.check(value) == value
        assert getattr(MeshOptions().resolved(DISTANCE), o.name) == (getattr(DISTANCE, o.weights) if o.weights else o.default)


@pytest.mark.parametrize("name,good,bad", [
    ("threshold", [1e-9, 0.5, 1 - 1e-9], [0, 1, 0.0, 1.0, -0.1, True, "0.5", math.nan, math.inf, 10 ** 400]),
    ("hole_closing", [0, 12, 3], [-1, 13, 1.5, 2.0, True, "1"]),
    ("pit_sealing", [0, 8], [-1, 9, True, "2"]),
    ("primitive_snap", [0, 0.0, 0.5, 0.999], [1, 1.0, -1e-4, True, math.nan, "0.1"]),
    ("silhouette_carve", [True, False], [0, 1, "true", []]),
    ("sph_hull_carve", [True, False], [0, 1, "on", []]),
    ("format", ["obj", "ply", "glb"], ["OBJ", "stl", "", 1]),
    ("up", ["y", "z"], ["Z", "x", "y ", True]),
])
def test_each_option_is_checked_once_with_one_message_style(name, good, bad):
    spec = BY_NAME[name]
    for value in good:
        kept = MeshOptions(**{name: value}).given()[name]
        assert kept == value and type(kept) is {"float": float, "int": int, "bool": bool, "choice": str}[spec.kind]
    for value in bad:
        with pytest.raises(OptionError) as exc:
            MeshOptions(**{name: value})
        assert str(exc.value).startswith(f"{name}: expected {spec.expected()}, got ") and exc.value.name == name


def test_ranges_are_the_records_own():
    assert BY_NAME["primitive_snap"].expected() == "a number in [0, 1)"
    assert BY_NAME["threshold"].expected() == "a number in (0, 1)"
    assert BY_NAME["hole_closing"].expected() == "an integer in [0, 12] (voxels)"
    assert BY_NAME["pit_sealing"].expected() == "an integer in [0, 8] (voxels)"


def test_overrides_merge_onto_the_weights_defaults():
    given = MeshOptions(threshold=0.3, pit_sealing=0)
    done = given.over(QUALITIES["fast"]).resolved(DISTANCE)
    assert (done.threshold, done.pit_sealing, done.hole_closing, done.test_time_mirror) == (0.3, 0, 1, False)
    assert MeshOptions(test_time_mirror=True).over(QUALITIES["fast"]).resolved(DISTANCE).test_time_mirror is True  # given wins
    assert QUALITIES[DEFAULT_QUALITY].resolved(DISTANCE) == MeshOptions().resolved(DISTANCE)  # best: the weights' own
    assert MeshOptions().resolved(DISTANCE).keep_fraction == 0.05 and MeshOptions(all_parts=True).resolved(DISTANCE).keep_fraction == 0.0


def test_options_the_weights_cannot_take_are_refused():
    shell = GeometryConfig(target="shell")
    for name, value in (("visible_fusion", True), ("pit_sealing", 2)):
        with pytest.raises(OptionError, match=f"^{name}: these weights predict the 'shell' target"):
            MeshOptions(**{name: value}).resolved(shell)
    assert MeshOptions(pit_sealing=0, visible_fusion=False).resolved(shell).pit_sealing == 0


def test_the_schema_lists_every_option_with_the_weights_defaults():
    sch = schema(DISTANCE)
    assert [e["name"] for e in sch["options"]] == [o.name for o in OPTIONS]
    by = {e["name"]: e for e in sch["options"]}
    assert by["threshold"]["default"] == 0.45 and by["pit_sealing"]["default"] == 4 and by["test_time_mirror"]["default"] is True
    assert by["format"]["default"] is None and by["format"]["choices"] == ["obj", "ply", "glb"] and by["texture"]["default"] is False
    assert by["hole_closing"] | {"default": None} == {"name": "hole_closing", "type": "int", "min": 0, "max": 12, "min_open": False,
                                                       "max_open": False, "choices": None, "default": None,
                                                       "label": BY_NAME["hole_closing"].label,
                                                       "help": BY_NAME["hole_closing"].help, "weights": "hole_closing"}
    assert {q["name"]: q["options"] for q in sch["qualities"]} == {"best": {}, "fast": {"test_time_mirror": False}}
    assert schema()["options"][0]["default"] is None  # without weights: the ones they would give are unknown


def _parser():
    parser = argparse.ArgumentParser(exit_on_error=False)
    add_arguments(parser)
    return parser


def test_the_cli_flags_are_made_from_the_record():
    parser = _parser()
    flags = {a.dest: a.option_strings for a in parser._actions if a.dest != "help"}
    for o in OPTIONS:
        assert o.flag in flags[o.name]
    assert "--no-test-time-mirror" in flags["test_time_mirror"] and "--quality" in flags["quality"]
    args = parser.parse_args(["--threshold", "0.3", "--no-test-time-mirror", "--texture", "--pit-sealing", "2", "--up", "z"])
    assert from_arguments(args).given() == {"threshold": 0.3, "test_time_mirror": False, "texture": True, "pit_sealing": 2, "up": "z"}
    assert from_arguments(parser.parse_args(["--quality", "fast"])).given() == {"test_time_mirror": False}
    assert from_arguments(parser.parse_args([])) == MeshOptions()
    for argv, message in ((["--pit-sealing", "9"], "--pit-sealing: expected an integer in [0, 8] (voxels), got 9"),
                          (["--primitive-snap", "1"], "--primitive-snap: expected a number in [0, 1), got 1"),
                          (["--threshold", "nan"], "--threshold: expected a number in (0, 1), got nan")):
        with pytest.raises(OptionError) as exc:
            from_arguments(parser.parse_args(argv))
        assert str(exc.value) == message


def test_request_options_are_parsed_from_the_record():
    import json

    show = json.dumps
    opts = parse_request_options({"threshold": 0.4, "hole_closing": None, "quality": "fast", "save_intermediates": "x"}, show,
                                 extra=("save_intermediates",))
    assert opts.given() == {"threshold": 0.4, "test_time_mirror": False}
    with pytest.raises(OptionError, match=r"^option 'threshold': expected a number in \(0, 1\), got true$"):
        parse_request_options({"threshold": True}, show)
    with pytest.raises(OptionError, match=r"^option 'quality': expected one of 'best', 'fast', got \"slow\"$"):
        parse_request_options({"quality": "slow"}, show)
    with pytest.raises(OptionError, match=r"^unknown option\(s\) \"thresh\"; known: threshold, "):
        parse_request_options({"thresh": None}, show)  # (an unknown key is refused even when null)


def test_the_steps_run_in_their_one_order():
    """Carves (the outline's, the map's hull), then fusion, pit sealing and back sealing: each step sees the grid the one
    before made."""
    from genre_backend.config import CameraConfig
    from genre_backend.geometry.visible_front import fuse_visible_surface, seal_back, seal_pits
    from genre_backend.geometry.spherical import sph_hull_ramp
    from genre_backend.geometry.voxels import silhouette_ramp
    from genre_backend.nets.outputs import View

    g = GeometryConfig(target="distance", image_size=32, voxel_size=16, sph_size=16, sph_pad=8)
    cam = CameraConfig()
    gen = torch.Generator().manual_seed(0)
    prob = torch.rand((16, 16, 16), generator=gen)
    mask = torch.zeros((32, 32), dtype=torch.bool)
    mask[8:24, 10:22] = True
    depth = torch.where(mask, torch.full((32, 32), 2.1), torch.zeros(32, 32))
    sph = torch.full((16, 16), 0.75)  # a ball of radius 0.25
    opts = MeshOptions(threshold=0.5, silhouette_carve=True, sph_hull_carve=True, visible_fusion=True, pit_sealing=2,
                       back_sealing=True).resolved(g)
    want = torch.minimum(prob, silhouette_ramp(mask[None], cam, 16)[0, 0])
    hull = sph_hull_ramp(sph[None], 16, g.sph_nohit_min, g.sph_hull_spread)[0, 0]
    assert 0 < int((hull < 1).sum()) < hull.numel() - 100  # it trims the corners and keeps the ball
    with_hull = torch.minimum(want, hull)
    want = seal_back(seal_pits(fuse_visible_surface(with_hull, depth, cam, g, 0.5), mask, cam, g, 0.5, 2), mask, cam, g, 0.5)
    view = View(mask, depth, cam, sph)
    assert torch.equal(opts.shape_grid(prob, view, g), want)
    # a view without a map (a row that has none) is not trimmed to one
    assert torch.equal(opts.shape_grid(prob, View(mask, depth, cam), g),
                       seal_back(seal_pits(fuse_visible_surface(torch.minimum(prob, silhouette_ramp(mask[None], cam, 16)[0, 0]),
                                                                depth, cam, g, 0.5), mask, cam, g, 0.5, 2), mask, cam, g, 0.5))
    off = MeshOptions(silhouette_carve=False, sph_hull_carve=False, visible_fusion=False, pit_sealing=0,
                      back_sealing=False).resolved(g)
    assert torch.equal(off.shape_grid(prob, view, g), prob)
    v, f, fit = off.snap_mesh("v", "f", view)  # snapping off: the mesh as it is, untouched
    assert (v, f, fit) == ("v", "f", None)


def test_min_part_share_drops_the_pieces_smaller_than_it():
    """The option added after the record (one field in options.py): its flag, its key, its row and its effect."""
    from genre_backend.geometry.cleanup import DEFAULT_KEEP_FRACTION

    spec = BY_NAME["min_part_share"]
    assert spec.default == DEFAULT_KEEP_FRACTION and spec.expected() == "a number in [0, 1]" and spec.weights is None
    assert MeshOptions().resolved(DISTANCE).keep_fraction == DEFAULT_KEEP_FRACTION
    assert MeshOptions(min_part_share=0.5).resolved(DISTANCE).keep_fraction == 0.5
    assert MeshOptions(min_part_share=0.5, all_parts=True).resolved(DISTANCE).keep_fraction == 0.0
    with pytest.raises(OptionError, match=r"^min_part_share: expected a number in \[0, 1\], got 1.5$"):
        MeshOptions(min_part_share=1.5)
    assert from_arguments(_parser().parse_args(["--min-part-share", "0.2"])).min_part_share == 0.2
    assert parse_request_options({"min_part_share": 0}, str).min_part_share == 0.0
    assert {e["name"]: e["default"] for e in schema(DISTANCE)["options"]}["min_part_share"] == DEFAULT_KEEP_FRACTION
    # two balls, the small one 1/8 of the large one's area: kept at 0.1, dropped at 0.2
    n = 32
    grid = torch.zeros((n, n, n))
    idx = torch.arange(n, dtype=torch.float32)
    x, y, z = torch.meshgrid(idx, idx, idx, indexing="ij")
    grid[((x - 10) ** 2 + (y - 16) ** 2 + (z - 16) ** 2) <= 36] = 1.0
    grid[((x - 24) ** 2 + (y - 16) ** 2 + (z - 16) ** 2) <= 4.4] = 1.0
    shell = GeometryConfig(target="shell", voxel_size=n)
    parts = []
    for share in (0.1, 0.2):
        _, v, f, report = MeshOptions(threshold=0.5, min_part_share=share).resolved(shell).mesh(grid, shell)
        parts.append(report.parts)
    assert parts == [2, 1]


@pytest.mark.parametrize("option", [o for o in OPTIONS if o.weights], ids=lambda o: o.name)
def test_each_option_accepts_what_a_weights_file_may_store_and_nothing_else(option):
    """An option that overrides a ``GeometryConfig`` field holds the same values as the field: a value that the
    record accepts loads from a weights file and one it refuses is refused there too (so a file's own setting can
    always be shown and overridden in the add-on's row, and no override can make what no file may hold)."""
    if option.kind == "bool":
        probes = [True, False, 0, 1, None, "yes"]
    else:
        step = 1 if option.kind == "int" else 1e-9
        probes = [option.lo, option.hi, option.lo - step, option.hi + step, (option.lo + option.hi) / 2,
                  math.nan, True, "0"]
        if option.kind == "int":
            probes[4] = int(probes[4])
    for value in probes:
        try:
            option.check(value)
            record = True
        except OptionError:
            record = False
        try:
            GeometryConfig(target="distance", **{option.weights: value})
            stored = True
        except (ValueError, TypeError):
            stored = False
        assert record == stored, (option.name, value, record, stored)
