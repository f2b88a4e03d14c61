"""``genre serve``: the JSON-lines protocol of docs/protocol.md, against a real server process."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import trimesh

from support.files import huge_png
from support.server import ServerProcess

REPO = Path(__file__).resolve().parents[3]


@pytest.fixture(scope="module")
def files(trained, tmp_path_factory):
    from PIL import Image
    import numpy as np

    d = tmp_path_factory.mktemp("serve")
    views = trained[1]
    rgb = np.asarray(Image.open(views / "box" / "view_000.png").convert("RGB"))
    mask = np.load(views / "box" / "view_000.npz")["mask"] > 0.5
    f = {"rgb": views / "box" / "view_000.png", "rgba": d / "rgba.png", "mask": d / "mask.png", "empty_mask": d / "empty.png",
         "small_mask": d / "small.png", "text": d / "text.png", "zero": d / "zero.png", "truncated": d / "trunc.png", "dir": d / "dir.png",
         "missing": d / "missing.png", "huge": d / "huge.png", "transparent": d / "transparent.png", "blocker": d / "blocker"}
    Image.fromarray(np.dstack([rgb, mask.astype(np.uint8) * 255]), "RGBA").save(f["rgba"])
    Image.fromarray(mask.astype(np.uint8) * 255, "L").save(f["mask"])
    Image.new("L", (64, 64), 0).save(f["empty_mask"])
    f["full_mask"] = d / "full.png"
    Image.new("L", rgb.shape[1::-1], 255).save(f["full_mask"])  # the whole photo: a doubtful mask
    Image.new("L", (32, 48), 255).save(f["small_mask"])
    Image.new("RGBA", (64, 64), (9, 9, 9, 0)).save(f["transparent"])
    f["text"].write_text("hello")
    f["zero"].write_bytes(b"")
    data = f["rgb"].read_bytes()
    f["truncated"].write_bytes(data[: len(data) // 2])
    f["dir"].mkdir()
    f["huge"].write_bytes(huge_png(30000, 30000))
    f["blocker"].write_text("a file, not a folder")
    f["out"] = d / "out"
    f["out"].mkdir()
    return f


@pytest.fixture(scope="module")
def server(trained):
    s = ServerProcess("--weights", str(trained[0]))
    ready = s.next(timeout=300)
    assert ready["type"] == "ready" and ready["protocol"] == 1 and ready["preset"] == "tiny" and ready["device"] == "cpu"
    yield s
    s.send({"type": "shutdown", "id": "end"})
    assert s.until(lambda e: e["type"] == "bye") [-1]["id"] == "end"
    assert s.close() == 0


def test_ready_and_version_publish_the_options_record(server, trained):
    """The schema of every mesh option (the add-on builds its rows from it), defaults from the loaded weights."""
    from genre_backend.inference.options import OPTIONS, QUALITIES
    from genre_backend.nets.model import load_model

    geometry = load_model(trained[0]).config.geometry
    server.send({"type": "version", "id": "v"})
    ev = server.until(lambda e: e["type"] == "version")[-1]
    entries = {o["name"]: o for o in ev["options"]}
    assert list(entries) == [o.name for o in OPTIONS]
    for o in OPTIONS:
        e = entries[o.name]
        assert set(e) == {"name", "type", "min", "max", "min_open", "max_open", "choices", "default", "label", "help", "weights"}
        assert e["type"] == o.kind and e["label"] and e["help"] and "\n" not in e["help"]
        assert e["default"] == (getattr(geometry, o.weights) if o.weights else o.default)
    assert entries["threshold"]["default"] == geometry.default_threshold and entries["threshold"]["min_open"] is True
    assert (entries["primitive_snap"]["min"], entries["primitive_snap"]["max"], entries["primitive_snap"]["max_open"]) == (0.0, 1.0, True)
    assert entries["up"]["choices"] == ["y", "z"] and entries["texture"]["default"] is False
    assert [q["name"] for q in ev["qualities"]] == list(QUALITIES) and {q["name"]: q["options"] for q in ev["qualities"]}["fast"] == {
        "test_time_mirror": False}
    server.send({"type": "reconstruct", "id": "bad-snap", "image": "a.png", "output": "b.obj", "options": {"primitive_snap": 1}})
    err = server.until(lambda e: e["type"] == "error")[-1]  # the one message style: WHERE: expected WHAT, got VALUE
    assert err["message"] == "option 'primitive_snap': expected a number in [0, 1), got 1", err


def _alive(server):
    server.send({"type": "ping", "id": "alive"})
    assert server.until(lambda e: e["type"] == "pong")[-1] == {"type": "pong", "id": "alive"}


def test_ping_and_version(server, trained):
    server.send({"type": "ping", "id": 7})
    assert server.next() == {"type": "pong", "id": 7}
    server.send({"type": "version", "id": "v"})
    v = server.next()
    assert v["type"] == "version" and v["id"] == "v" and v["weights"] == str(trained[0]) and v["preset"] == "tiny" and v["protocol"] == 1
    from genre_backend.nets.model import load_model

    assert v["threshold"] == load_model(trained[0]).config.geometry.default_threshold


@pytest.mark.parametrize(
    "line, code, rid",
    [
        ("{not json", "bad_json", None),
        ("[1, 2]", "bad_json", None),
        ('"text"', "bad_json", None),
        ('{"id": 3}', "missing_field", 3),
        ('{"type": "explode", "id": 4}', "unknown_type", 4),
        ('{"type": "reconstruct", "image": "a.png", "output": "b.obj"}', "missing_field", None),
        ('{"type": "reconstruct", "id": 5, "output": "b.obj"}', "missing_field", 5),
        ('{"type": "reconstruct", "id": 6, "image": "a.png"}', "missing_field", 6),
        ('{"type": "reconstruct", "id": 7, "image": 12, "output": "b.obj"}', "bad_field", 7),
        ('{"type": "reconstruct", "id": 8, "image": "a.png", "output": "b.obj", "options": {"threshold": 1.5}}', "bad_field", 8),
        ('{"type": "reconstruct", "id": 9, "image": "a.png", "output": "b.obj", "options": {"format": "stl"}}', "bad_field", 9),
        ('{"type": "reconstruct", "id": 10, "image": "a.png", "output": "b.obj", "options": [1]}', "bad_field", 10),
        ('{"type": "reconstruct", "id": 11, "image": "a.png", "output": "b.obj", "options": {"thresh": 0.4}}', "bad_field", 11),
        ('{"type": "reconstruct", "id": 12, "image": "a.png", "output": "b.obj", "options": {"texture": "yes"}}', "bad_field", 12),
        ('{"type": "reconstruct", "id": 13, "image": "a.png", "output": "b.obj", "options": {"all_parts": 1}}', "bad_field", 13),
        ('{"type": "reconstruct", "id": 14, "image": "a.png", "output": "b.obj", "options": {"pit_sealing": 9}}', "bad_field", 14),
        ('{"type": "reconstruct", "id": 15, "image": "a.png", "output": "b.obj", "options": {"hole_closing": 1.5}}', "bad_field", 15),
        ('{"type": "reconstruct", "id": 16, "image": "a.png", "output": "b.obj", "options": {"hole_closing": true}}', "bad_field", 16),
        ('{"type": "reconstruct", "id": 17, "image": "a.png", "output": "b.obj", "options": {"silhouette_carve": 1}}', "bad_field", 17),
        ('{"type": "reconstruct", "id": 18, "image": "a.png", "output": "b.obj", "options": {"silhouette_carve": "yes"}}', "bad_field", 18),
        ('{"type": "reconstruct", "id": 19, "image": "a.png", "output": "b.obj", "options": {"visible_fusion": 0}}', "bad_field", 19),
        ('{"type": "reconstruct", "id": 20, "image": "a.png", "output": "b.obj", "options": {"visible_fusion": "on"}}', "bad_field", 20),
        ('{"type": "reconstruct", "id": 21, "image": "a.png", "output": "b.obj", "options": {"primitive_snap": 1.5}}', "bad_field", 21),
        ('{"type": "reconstruct", "id": 22, "image": "a.png", "output": "b.obj", "options": {"primitive_snap": true}}', "bad_field", 22),
        ('{"type": "reconstruct", "id": 23, "image": "a.png", "output": "b.obj", "options": {"primitive_snap": -0.1}}', "bad_field", 23),
        ('{"type": "reconstruct", "id": 24, "image": "a.png", "output": "b.obj", "options": {"test_time_mirror": 1}}', "bad_field", 24),
        ('{"type": "reconstruct", "id": 25, "image": "a.png", "output": "b.obj", "options": {"test_time_mirror": "on"}}', "bad_field", 25),
        ('{"type": "reconstruct", "id": 26, "image": "a.png", "output": "b.obj", "options": {"pit_sealing": 9}}', "bad_field", 26),
        ('{"type": "reconstruct", "id": 27, "image": "a.png", "output": "b.obj", "options": {"pit_sealing": true}}', "bad_field", 27),
        ('{"type": "reconstruct", "id": 28, "image": "a.png", "output": "b.obj", "options": {"quality": "slow"}}', "bad_field", 28),
        ('{"type": "reconstruct", "id": 29, "image": "a.png", "output": "b.obj", "options": {"quality": 1}}', "bad_field", 29),
        ('{"type": "reconstruct", "id": true, "image": "a.png", "output": "b.obj"}', "bad_field", None),
        ('{"type": "cancel"}', "missing_field", None),
        ('{"type": "cancel", "id": "nobody"}', "unknown_job", "nobody"),
    ],
)
def test_malformed_requests_get_error_events(server, line, code, rid):
    server.send(line)
    ev = server.next()
    assert ev["type"] == "error" and ev["code"] == code and ev["id"] == rid, ev
    assert "\n" not in ev["message"] and ev["message"]
    _alive(server)


@pytest.mark.slow
def test_reconstruct_reports_progress_and_result(server, files, trained):
    out = files["out"] / "box.ply"
    server.send({"type": "reconstruct", "id": "job1", "image": str(files["rgb"]), "output": str(out), "options": {"threshold": 0.45, "hole_closing": 2, "silhouette_carve": True, "visible_fusion": True, "primitive_snap": 0.99, "test_time_mirror": True,
                                                                                                                "pit_sealing": 3, "quality": "fast",
                                                                                                                "save_intermediates": str(files["out"] / "inter")}})
    events = server.until(lambda e: e["type"] in ("result", "error"))
    result = events[-1]
    assert result["type"] == "result", result
    progress = [e for e in events if e["type"] == "progress"]
    assert [e["stage"] for e in progress] == ["load", "preprocess", "depth", "partial_sph", "inpaint", "voxels", "refine", "mesh", "write"]
    assert all(e["id"] == "job1" for e in events)
    fr = [e["fraction"] for e in progress]
    assert fr == sorted(fr) and 0 <= fr[0] and fr[-1] <= 1
    assert result["mesh"] == str(out) and result["format"] == "ply" and result["mask_source"] == "salient"
    assert result["threshold"] == 0.45  # the option, not the weights' level (0.5 here)
    assert result["hole_closing"] == 2 and result["silhouette_carve"] is True and result["visible_fusion"] is True  # likewise
    assert result["primitive"] in ("box", "cylinder", "cone", "torus", "ellipsoid") and result["primitive_snap"] == 0.99  # (so loose a tolerance always snaps)
    assert result["test_time_mirror"] is True and result["pit_sealing"] == 3  # (an option given wins over the quality's set)
    assert result["faces"] == len(trimesh.load(out, force="mesh").faces) > 0
    assert set(result["timings"]) >= {"depth", "refine", "mesh", "write"}
    cam = result["camera"]
    assert {k: cam[k] for k in ("lens_mm", "sensor_mm", "distance")} == {"lens_mm": 50.0, "sensor_mm": 30.594, "distance": 2.2}
    # where the backend's square view lies in the photo: the photo's size, and a square crop box
    from PIL import Image

    with Image.open(files["rgb"]) as im:
        assert cam["image_size"] == list(im.size)
    assert cam["exif_orientation"] == 1  # a file without the tag (the add-on's test turns a tagged one)
    x0, y0, x1, y1 = cam["crop_box"]
    assert x1 - x0 == pytest.approx(y1 - y0) and x1 > x0
    assert (files["out"] / "inter" / "depth.png").is_file()
    # mask file and alpha are reported as such
    server.send({"type": "reconstruct", "id": "job2", "image": str(files["rgb"]), "mask": str(files["mask"]), "output": str(files["out"] / "m.glb")})
    r = server.until(lambda e: e["type"] in ("result", "error"))[-1]
    assert r["mask_source"] == "file" and r["mask_warning"] is None
    from genre_backend.nets.model import load_model

    assert r["threshold"] == load_model(trained[0]).config.geometry.default_threshold
    assert r["hole_closing"] == load_model(trained[0]).config.geometry.hole_closing
    assert r["silhouette_carve"] is load_model(trained[0]).config.geometry.silhouette_carve is False
    assert r["visible_fusion"] is load_model(trained[0]).config.geometry.visible_fusion is False
    assert r["primitive"] is None and load_model(trained[0]).config.geometry.primitive_snap == 0.0  # weights without it: off
    assert r["test_time_mirror"] is load_model(trained[0]).config.geometry.test_time_mirror is False
    server.send({"type": "reconstruct", "id": "job3", "image": str(files["rgba"]), "output": str(files["out"] / "a.obj")})
    r = server.until(lambda e: e["type"] in ("result", "error"))[-1]
    assert r["mask_source"] == "alpha" and r["format"] == "obj"
    assert r["files"] == [str(files["out"] / "a.obj")] and r["parts"] >= 1 and r["parts_dropped"] >= 0
    mesh = trimesh.load(files["out"] / "a.obj", process=False)
    assert r["watertight"] == bool(mesh.is_watertight and mesh.is_winding_consistent)
    # colour from the photo: the OBJ's material and texture beside it, listed in the result
    out = files["out"] / "col.obj"
    server.send({"type": "reconstruct", "id": "job4", "image": str(files["rgba"]), "output": str(out), "options": {"texture": True, "all_parts": True}})
    r = server.until(lambda e: e["type"] in ("result", "error"))[-1]
    assert r["type"] == "result", r
    assert r["files"] == [str(out), str(out.with_suffix(".mtl")), str(files["out"] / "col_texture.png")]
    back = trimesh.load(out, process=False)
    assert len(back.visual.uv) == len(back.vertices) and back.visual.material.image is not None


def test_result_says_when_the_mask_is_doubtful(server, files):
    server.send({"type": "reconstruct", "id": "frame", "image": str(files["rgb"]), "mask": str(files["full_mask"]), "output": str(files["out"] / "f.obj")})
    r = server.until(lambda e: e["type"] in ("result", "error"))[-1]
    assert r["type"] == "result" and r["mask_source"] == "file" and r["faces"] > 0
    assert r["mask_warning"] == "the mask covers 100% of the photo and touches 100% of its border: it is probably the photo's frame, not the object"
    server.send({"type": "reconstruct", "id": "auto", "image": str(files["rgb"]), "output": str(files["out"] / "g.obj")})
    r = server.until(lambda e: e["type"] in ("result", "error"))[-1]
    assert r["type"] == "result" and r["mask_source"] == "salient" and r["mask_warning"] is None


@pytest.mark.parametrize(
    "image, mask, output, code, text",
    [
        ("text", None, "o.obj", "bad_image", "not an image"),
        ("zero", None, "o.obj", "bad_image", "0 bytes"),
        ("truncated", None, "o.obj", "bad_image", "truncated"),
        ("dir", None, "o.obj", "bad_image", "is a directory"),
        ("missing", None, "o.obj", "bad_image", "no such file"),
        ("huge", None, "o.obj", "bad_image", "too large"),
        ("transparent", None, "o.obj", "no_object", "no object"),
        ("rgb", "empty_mask", "o.obj", "bad_mask", "empty mask"),
        ("rgb", "small_mask", "o.obj", "bad_mask", "mask is 32×48"),
        ("rgb", "text", "o.obj", "bad_mask", "not an image"),
        ("rgba", None, "blocker/o.obj", "output_unwritable", "does not exist"),
        ("rgba", None, ".", "output_unwritable", "is a directory"),
    ],
)
def test_bad_inputs_give_an_error_and_the_server_goes_on(server, files, image, mask, output, code, text):
    req = {"type": "reconstruct", "id": f"bad-{image}-{code}", "image": str(files[image]), "output": str(files["out"] / output)}
    if mask:
        req["mask"] = str(files[mask])
    server.send(req)
    ev = server.until(lambda e: e["type"] in ("result", "error"))[-1]
    assert ev["type"] == "error" and ev["id"] == req["id"] and ev["code"] == code and text in ev["message"], ev
    _alive(server)


def test_cancel_running_and_queued_jobs(server, files):
    job = {"type": "reconstruct", "image": str(files["rgba"])}
    # one write, so the cancels reach the server before the ~0.1 s job can end even on a loaded machine
    server.send("\n".join(json.dumps(m) for m in (
        {**job, "id": "c1", "output": str(files["out"] / "c1.obj")},
        {**job, "id": "c2", "output": str(files["out"] / "c2.obj")},
        {"type": "cancel", "id": "c2"},  # still queued: answered at once
        {"type": "cancel", "id": "c1"},  # running: stops at the next stage boundary
    )))
    events = server.until(lambda e: e["type"] == "cancelled" and e["id"] == "c1")
    assert {"type": "cancelled", "id": "c2"} in events
    assert not any(e["type"] in ("result", "error") for e in events)
    assert not (files["out"] / "c1.obj").exists() and not (files["out"] / "c2.obj").exists()
    # the id is free again and the server goes on
    server.send({**job, "id": "c1", "output": str(files["out"] / "c1.obj")})
    assert server.until(lambda e: e["type"] in ("result", "error"))[-1]["type"] == "result"


def test_duplicate_job_id_is_refused(server, files):
    job = {"type": "reconstruct", "id": "dup", "image": str(files["rgba"]), "output": str(files["out"] / "dup.obj")}
    server.send(json.dumps(job) + "\n" + json.dumps(job))  # one write: the first cannot end before the second arrives
    events = server.until(lambda e: e["type"] == "result")
    assert any(e["type"] == "error" and e["code"] == "bad_field" and e["id"] == "dup" for e in events)


@pytest.mark.slow
def test_end_of_input_finishes_queued_jobs_then_exits(trained, files):
    s = ServerProcess("--weights", str(trained[0]))
    assert s.next(timeout=300)["type"] == "ready"
    s.send({"type": "reconstruct", "id": 1, "image": str(files["rgba"]), "output": str(files["out"] / "eof.obj")})
    assert s.close() == 0
    events = []
    while (ev := s.next()) is not None:
        events.append(ev)
    assert events[-2]["type"] == "result" and events[-1] == {"type": "bye", "id": None}
    assert all(line.endswith("\n") for line in s.raw)
    assert "genre serve" in s.proc.stderr.read()  # logs go to stderr


def test_bad_weights_give_an_error_event_and_exit_1(tmp_path):
    corrupt = tmp_path / "w.safetensors"
    corrupt.write_bytes(b"garbage" * 10)
    s = ServerProcess("--weights", str(corrupt))
    ev = s.next(timeout=300)
    assert ev["type"] == "error" and ev["code"] == "bad_weights" and ev["id"] is None
    assert s.close() == 1
