"""docs/FORMATS.md documents what the code writes, and nothing user-facing points to DESIGN.md.

The result keys are taken from a real estimate (mNBP postures, self-calibrated
rig), not from a list kept by hand, so a new field without documentation fails
here.
"""

from __future__ import annotations

import dataclasses
import json
import re
import struct
from pathlib import Path

import numpy as np
import pytest

DOC = Path(__file__).resolve().parent.parent / "docs" / "FORMATS.md"


@pytest.fixture(scope="module")
def doc() -> str:
    assert DOC.is_file(), f"{DOC} is missing"
    return DOC.read_text()


def _documented(doc: str) -> set[str]:
    """Names written as inline code in the document's text and tables (`name`, or a dotted path's parts)."""
    names = set()
    prose = re.sub(r"```.*?```", "", doc, flags=re.S)  # inline code outside the examples
    for code in re.findall(r"`([^`\n]+)`", prose):
        names.update(re.findall(r"[A-Za-z_][A-Za-z0-9_]*", code))
    return names


@pytest.fixture(scope="module")
def sequence():
    from estimator.synth import SynthSpec, synthesize

    return synthesize(SynthSpec(n_cameras=2, n_frames=12, seed=1, image_size=(320, 240)))


@pytest.fixture(scope="module")
def result(sequence, small_model) -> dict:
    from estimator.mnbp import measure_postures
    from estimator.pipeline import estimate_walk, tracks_from_sequence
    from estimator.rig import calibrate_rig
    from estimator.windows import Segment, SegmentedWalk

    est = estimate_walk(tracks_from_sequence(sequence), small_model)
    measured = measure_postures(est)
    est = dataclasses.replace(measured, rig=calibrate_rig(measured))
    out = est.to_result()
    # The same estimate as the one segment of a recording: adds segments, windows, frames[].segment.
    n = len(est.phase)
    window = {"first_index": 0, "last_index": n - 1, "segment": 0,
              "cameras": {c: {k: v[k] for k in ("azimuth_deg", "elevation_deg")} for c, v in out["cameras"].items()}}
    segmented = SegmentedWalk([Segment(0, n, 0, n - 1, est, 1)], [window]).to_result()
    json.dumps(out, allow_nan=False)  # strict JSON, as documented
    return {"walk": out, "segmented": segmented}


def test_result_keys_are_documented(doc, result):
    names = _documented(doc)
    out = result["walk"]
    # The optional fields the document promises are there for a self-calibrated rig.
    assert out["rig"]["source"] == "self-calibration", out["notes"]
    frame = out["frames"][0]
    for key in ("rig", "body"):
        assert key in out
    for key in ("person_joints3d", "model_joints2d"):
        assert key in frame
    keys = {
        "top level": set(out) | set(result["segmented"]),
        "frames[]": set().union(*(f.keys() for f in result["segmented"]["frames"])),
        "cameras": set().union(*(c.keys() for c in out["cameras"].values())),
        "motion_cue": set().union(*(c["motion_cue"].keys() for c in out["cameras"].values() if c["motion_cue"])),
        "hmm": set(out["hmm"]),
        "rig": set(out["rig"]),
        "rig.cameras": set().union(*(c.keys() for c in out["rig"]["cameras"].values())),
        "body": set(out["body"]) | set().union(*(s.keys() for s in out["body"]["segments"].values())),
        "body.segments": set(out["body"]["segments"]),
        "segments[]": set().union(*(s.keys() for s in result["segmented"]["segments"])),
        "windows[]": set().union(*(w.keys() for w in result["segmented"]["windows"])),
    }
    missing = {where: sorted(k - names) for where, k in keys.items() if k - names}
    assert not missing, f"keys not documented in docs/FORMATS.md: {missing}"
    assert {"segments", "windows"} <= keys["top level"] and "segment" in keys["frames[]"]


def test_conventions_are_documented(doc):
    from estimator.joints import JOINT_NAMES

    names = _documented(doc)
    assert set(JOINT_NAMES) <= names
    # The 13 joints appear in their order.
    positions = [doc.index(f"`{n}`") for n in JOINT_NAMES]
    assert positions == sorted(positions)
    for phrase in ("R_c R_ref^T", "x forward", "y the walker's left", "z up", "0 = right heel strike",
                   "0.5 = left heel strike", "counter-clockwise seen from above", "[0, 360)",
                   "u right, v down", "metres", "pixels", "degrees"):
        assert phrase in doc, phrase


def test_sequence_and_selfcal_keys_are_documented(doc, sequence):
    from estimator.selfcal import self_calibrate
    from service.cli.selfcal import result_to_json

    names = _documented(doc)
    assert set(sequence.rig()) <= names  # rig.json
    assert set(sequence.truth) <= names | {"damage"}  # truth.json of posecal synth
    assert set(sequence.truth["frames"][0]) <= names
    assert set(next(iter(sequence.truth["cameras"].values()))) <= names
    cams = list(sequence.cameras)
    tracks = np.array([[f["joints2d"][c] for f in sequence.truth["frames"]] for c in cams], float)
    for refine in (False, True):
        cal = self_calibrate(tracks, refine=refine)
        assert cal, cal.reason
        out = result_to_json(cal, cams)
        keys = set(out) | set().union(*(c.keys() for c in out["cameras"].values())) | set(out["frames"][0])
        assert keys <= names, sorted(keys - names)
        assert f'"{out["method"].split("+")[0]}"' in doc


def test_wire_header_fields_are_documented(doc):
    from capture.wire import (MAGIC, WIRE_VERSION, Box, FeedbackMessage, Quality, SilhouetteMessage, encode,
                              estimate_key, feedback_key, silhouette_key)

    names = _documented(doc)
    mask = np.full((4, 3), 255, np.uint8)
    msgs = [SilhouetteMessage(rig="lab", camera="c0", frame_index=1, capture_ns=2, box=Box(1, 2, 3, 4),
                              image_size=(640, 480), epoch_ns=1, seq=0, mask=mask, sync="index",
                              n_candidates=1, quality=Quality(1.0, 12.0, 0.9)),
            FeedbackMessage(rig="lab", camera="c0", frame_index=1, box=Box(1, 2, 3, 4), image_size=(640, 480),
                            mask=mask, issued_ns=5, epoch_ns=1)]
    for msg in msgs:
        payload = encode(msg)
        magic, version, kind, n = struct.unpack(">4sBBI", payload[:10])
        assert magic == MAGIC and version == WIRE_VERSION and f"{kind} = " in doc
        header = json.loads(payload[10:10 + n])
        fields = set(header) | set(header.get("quality", {}))
        assert fields <= names, sorted(fields - names)
    assert f"wire version, currently {WIRE_VERSION}" in doc and f"`{MAGIC.decode()}`" in doc
    for key in ("posecal/<rig>/<camera>/silhouette", "posecal/<rig>/<camera>/feedback", "posecal/<rig>/estimate"):
        assert f"`{key}`" in doc
    assert silhouette_key("lab", "c0") == "posecal/lab/c0/silhouette"
    assert feedback_key("lab", "c0") == "posecal/lab/c0/feedback" and estimate_key("lab") == "posecal/lab/estimate"


def _help(capsys, argv: list[str]) -> str:
    from service.cli import main

    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 0
    return capsys.readouterr().out


def test_cli_help_does_not_point_outside_the_repo(capsys):
    from service.cli import build_parser

    parser = build_parser()
    sub = next(a for a in parser._actions if a.__class__.__name__ == "_SubParsersAction")
    commands = list(sub.choices)
    assert {"estimate", "selfcal", "synth"} <= set(commands)
    for argv in [["--help"]] + [[c, "--help"] for c in commands]:
        text = _help(capsys, argv)
        assert text.strip(), argv
        assert "DESIGN.md" not in text, argv
    assert "docs/FORMATS.md" in _help(capsys, ["estimate", "--help"])
    assert "docs/FORMATS.md" in _help(capsys, ["selfcal", "--help"])


def test_openapi_does_not_point_outside_the_repo():
    from service.app import create_app

    text = json.dumps(create_app().openapi())
    assert "DESIGN.md" not in text
    assert "docs/FORMATS.md" in text


def test_upload_error_points_to_the_formats_doc(tmp_path):
    from service.intake import UploadError, _find_sequence_root

    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    with pytest.raises(UploadError) as exc:
        _find_sequence_root(tmp_path)
    assert "DESIGN.md" not in str(exc.value) and "docs/FORMATS.md" in str(exc.value)
