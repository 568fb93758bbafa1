"""The wire module: round trips, versioning, and rejection of malformed payloads."""

from __future__ import annotations

import json
import struct

import numpy as np
import pytest

from capture.wire import (
    WIRE_VERSION,
    Box,
    FeedbackMessage,
    Quality,
    SilhouetteMessage,
    WireError,
    decode,
    encode,
    estimate_key,
    feedback_key,
    parse_key,
    silhouette_key,
)


def _mask(h: int = 30, w: int = 12) -> np.ndarray:
    m = np.zeros((h, w), np.uint8)
    m[5:25, 2:10] = 255
    m[10, 5] = 0  # a hole, so the PNG is not trivially uniform
    return m


def _silhouette(**overrides) -> SilhouetteMessage:
    fields = dict(rig="lab", camera="c1", frame_index=42, capture_ns=1_700_000_000_123_456_789,
                  box=Box(100, 50, 12, 30), image_size=(640, 480),
                  epoch_ns=1_700_000_000_000_000_000,
                  seq=7, mask=_mask(), sync="index", publish_ns=1_700_000_000_124_000_000)
    fields.update(overrides)
    return SilhouetteMessage(**fields)


def test_silhouette_round_trip_keeps_every_field():
    msg = _silhouette()
    out = decode(encode(msg))
    assert isinstance(out, SilhouetteMessage)
    assert out == msg  # every metadata field (mask excluded from ==)
    np.testing.assert_array_equal(out.mask, msg.mask)
    full = out.full_mask()
    assert full.shape == (480, 640) and np.count_nonzero(full) == np.count_nonzero(msg.mask)
    assert full[50 + 5, 100 + 2] == 255


def test_empty_silhouette_round_trip():
    msg = _silhouette(box=Box(0, 0, 0, 0), mask=np.zeros((0, 0), np.uint8))
    out = decode(encode(msg))
    assert out.box.empty and out.mask.size == 0 and out.seq == msg.seq


def test_feedback_round_trip_with_soft_prior():
    prior = np.linspace(0, 255, 40 * 20).astype(np.uint8).reshape(40, 20)
    msg = FeedbackMessage(rig="lab", camera="c1", frame_index=9, box=Box(0, 0, 20, 40),
                          image_size=(320, 240), mask=prior, issued_ns=5)
    out = decode(encode(msg), expect=FeedbackMessage)
    np.testing.assert_array_equal(out.mask, prior)
    with pytest.raises(WireError, match="expected a SilhouetteMessage"):
        decode(encode(msg), expect=SilhouetteMessage)


def _envelope(header: dict, png: bytes = b"", *, version: int = WIRE_VERSION,
              kind: int = 1) -> bytes:
    head = json.dumps(header).encode()
    return struct.pack(">4sBBI", b"PCAL", version, kind, len(head)) + head + png


def _header_and_png(msg: SilhouetteMessage | None = None) -> tuple[dict, bytes]:
    payload = encode(msg or _silhouette())
    n = struct.unpack_from(">I", payload, 6)[0]
    return json.loads(payload[10:10 + n]), payload[10 + n:]


@pytest.mark.parametrize("mutate, reason", [
    (lambda h, p: b"", "too short"),
    (lambda h, p: b"XXXX" + encode(_silhouette())[4:], "bad magic"),
    (lambda h, p: _envelope(h, p, version=WIRE_VERSION + 1), "unsupported wire version"),
    (lambda h, p: _envelope(h, p, kind=9), "unknown message kind"),
    (lambda h, p: encode(_silhouette())[:10] + b"{not json", "exceeds the payload|not JSON"),
    (lambda h, p: _envelope({**h, "frame_index": "3"}, p), "frame_index"),
    (lambda h, p: _envelope({**h, "frame_index": -1}, p), "frame_index must be >= 0"),
    (lambda h, p: _envelope({**h, "box": [630, 0, 12, 30]}, p), "not inside the image"),
    (lambda h, p: _envelope({**h, "box": [100, 50, 13, 30]}, p), "does not match box size"),
    (lambda h, p: _envelope(h, p[:20]), "not a decodable PNG"),
    (lambda h, p: _envelope({**h, "rig": "a/b"}, p), "rig must match"),
    (lambda h, p: _envelope({**h, "sync": "maybe"}, p), "sync must be"),
    (lambda h, p: _envelope({k: v for k, v in h.items() if k != "seq"}, p), "'seq'"),
    (lambda h, p: _envelope({**h, "box": [0, 0, 0, 0]}, p), "empty box but a PNG"),
])
def test_malformed_payloads_are_rejected_with_a_reason(mutate, reason):
    header, png = _header_and_png()
    with pytest.raises(WireError, match=reason):
        decode(mutate(header, png))


def test_non_binary_silhouette_is_rejected():
    with pytest.raises(WireError, match="binary"):
        _silhouette(mask=np.full((30, 12), 7, np.uint8))


def test_keys():
    assert silhouette_key("lab", "c1") == "posecal/lab/c1/silhouette"
    assert feedback_key("lab", "*") == "posecal/lab/*/feedback"
    assert estimate_key("lab") == "posecal/lab/estimate"
    assert parse_key("posecal/lab/c1/feedback") == ("lab", "c1", "feedback")
    assert parse_key("posecal/lab/estimate") == ("lab", None, "estimate")
    for bad in ("posecal/lab/c1/other", "other/lab/c1/silhouette", "posecal/lab/*/silhouette"):
        with pytest.raises(WireError):
            parse_key(bad)
    with pytest.raises(WireError):
        silhouette_key("a b", "c1")


# ------------------------------------------------------------ quality fields (issue 17)


def test_candidates_and_quality_round_trip():
    quality = Quality(walker_fraction=0.75, area_median=1234.5, stability=0.9)
    out = decode(encode(_silhouette(n_candidates=3, quality=quality)))
    assert out.n_candidates == 3 and out.quality == quality
    unsteady = decode(encode(_silhouette(n_candidates=0, quality=Quality(0.0, 0.0))))
    assert unsteady.n_candidates == 0 and unsteady.quality.stability is None


def test_track_id_round_trips_and_is_left_out_when_none():
    assert decode(encode(_silhouette(track_id=2))).track_id == 2
    moved = decode(encode(_silhouette(track_id=1, track_from=30)))
    assert (moved.track_id, moved.track_from) == (1, 30)
    header, _ = _header_and_png()
    assert "track_id" not in header and "track_from" not in header
    assert decode(encode(_silhouette())).track_id is None


def test_a_message_without_them_leaves_them_out_and_old_headers_decode():
    header, png = _header_and_png()
    assert "n_candidates" not in header and "quality" not in header  # None is not sent
    old = decode(_envelope(header, png))  # what an agent before these fields sent
    assert old == _silhouette() and old.n_candidates is None and old.quality is None
    header, _ = _header_and_png(_silhouette(quality=Quality(0.5, 10.0)))
    assert header["quality"] == {"walker_fraction": 0.5, "area_median": 10.0}  # no stability yet


@pytest.mark.parametrize("fields, reason", [
    ({"n_candidates": -1}, r"n_candidates must be an integer in \[0, 65536\]"),
    ({"n_candidates": 70000}, r"n_candidates must be an integer in \[0, 65536\]"),
    ({"n_candidates": "2"}, "'n_candidates' must be an integer"),
    ({"n_candidates": True}, "'n_candidates' must be an integer"),
    ({"n_candidates": None}, "'n_candidates' must be an integer"),  # absent is fine, null is not
    ({"track_id": -1}, "track_id must be an integer >= 0"),
    ({"track_id": 1.0}, "'track_id' must be an integer"),
    ({"track_id": None}, "'track_id' must be an integer"),
    ({"track_id": 1, "track_from": 43}, r"track_from must be a frame index from 0 to frame_index \(42\)"),
    ({"track_id": 1, "track_from": -1}, "track_from must be a frame index"),
    ({"track_id": 0, "track_from": 10}, "with a track_id of 1 or more"),
    ({"track_from": 10}, "with a track_id of 1 or more"),
    ({"track_id": 1, "track_from": 1.5}, "'track_from' must be an integer"),
    ({"quality": [0.5, 10, 1]}, "'quality' must be an object"),
    ({"quality": {"area_median": 10}}, r"quality.walker_fraction must be a number in \[0, 1\], got None"),
    ({"quality": {"walker_fraction": 1.5, "area_median": 10}}, r"walker_fraction must be a number in \[0, 1\]"),
    ({"quality": {"walker_fraction": "all", "area_median": 10}}, "walker_fraction must be a number"),
    ({"quality": {"walker_fraction": 0.5, "area_median": -1}}, "area_median must be a number"),
    ({"quality": {"walker_fraction": 0.5, "area_median": 10, "stability": 2}}, r"stability must be a number in \[0, 1\]"),
    ({"quality": {"walker_fraction": 0.5, "area_median": 640 * 480 + 1}}, "exceeds the image"),
])
def test_bad_candidates_or_quality_are_rejected_with_a_reason(fields, reason):
    header, png = _header_and_png()
    with pytest.raises(WireError, match=reason):
        decode(_envelope({**header, **fields}, png))


@pytest.mark.parametrize("token", ["NaN", "Infinity", "-Infinity"])
def test_non_finite_quality_is_rejected(token):
    """json.loads reads NaN and Infinity; the wire does not carry them."""
    header, png = _header_and_png()
    head = json.dumps({**header, "quality": {"walker_fraction": 0.5, "area_median": 1.0}})
    head = head.replace('"area_median": 1.0', f'"area_median": {token}').encode()
    with pytest.raises(WireError, match="area_median must be a number"):
        decode(struct.pack(">4sBBI", b"PCAL", WIRE_VERSION, 1, len(head)) + head + png)
    with pytest.raises(WireError, match="stability must be a number"):
        Quality(0.5, 1.0, stability=float(token.replace("Infinity", "inf")))


# ------------------------------------------------------------ a detector's keypoints (issue 18)


def _keypoints() -> np.ndarray:
    points = np.column_stack([np.linspace(100, 112, 13), np.linspace(50, 80, 13)])
    points[4] = np.nan  # a missed joint
    return points


def test_keypoints_round_trip_as_pairs_and_nulls():
    msg = _silhouette(keypoints=_keypoints())
    header, _ = _header_and_png(msg)
    assert len(header["keypoints"]) == 13 and header["keypoints"][4] is None and header["keypoints"][0] == [100, 50]
    out = decode(encode(msg))
    np.testing.assert_allclose(out.keypoints, _keypoints(), atol=0.005)  # to a hundredth of a pixel
    assert decode(encode(_silhouette())).keypoints is None  # not sent, not there
    header, png = _header_and_png()
    assert decode(_envelope({**header, "keypoints": [None] * 13}, png)).keypoints is None  # none placed
    given = _keypoints()
    msg = _silhouette(keypoints=given)
    given[0] = np.inf  # the caller's array changes afterwards: the message's copy does not
    assert np.isfinite(msg.keypoints[0]).all() and not msg.keypoints.flags.writeable
    json.loads(encode(msg)[10:10 + struct.unpack(">I", encode(msg)[6:10])[0]])  # strict JSON still


def test_keypoints_for_frame_leaves_out_joints_far_outside_it():
    from capture.wire import keypoints_for_frame

    points = _keypoints()
    points[0] = (5000.0, 50.0)  # a detector's stray joint across the room
    kept = keypoints_for_frame(points, (640, 480))
    assert np.isnan(kept[0]).all() and np.isnan(kept[4]).all() and np.array_equal(kept[1:4], points[1:4])
    assert keypoints_for_frame(np.full((13, 2), np.nan), (640, 480)) is None
    assert keypoints_for_frame(None, (640, 480)) is None
    with pytest.raises(WireError, match="within the image's size"):
        _silhouette(keypoints=points)


@pytest.mark.parametrize("value, reason", [
    ([[1, 2]] * 12, "must be a list of 13"),
    ([[1, 2, 3]] + [[1, 2]] * 12, "must be a list of 13"),
    ([["1", 2]] + [[1, 2]] * 12, "must be a list of 13"),
    ([[True, 2]] + [[1, 2]] * 12, "must be a list of 13"),
    ({"x": 1}, "must be a list of 13"),
    ([[1e5, 2]] + [[1, 2]] * 12, "within the image's size"),
    ([[10 ** 400, 2]] + [[1, 2]] * 12, "must be a list of 13"),  # no OverflowError: a WireError
    ([[1e300, 2]] + [[1, 2]] * 12, "must be a list of 13"),
])
def test_bad_keypoints_are_rejected_with_a_reason(value, reason):
    header, png = _header_and_png()
    with pytest.raises(WireError, match=reason):
        decode(_envelope({**header, "keypoints": value}, png))


@pytest.mark.parametrize("token", ["NaN", "Infinity", "-Infinity"])
def test_non_finite_keypoints_are_rejected(token):
    """json.loads reads NaN and Infinity; a keypoint is a finite pixel or null."""
    header, png = _header_and_png()
    head = json.dumps({**header, "keypoints": [[1.5, 2.0]] * 13}).replace("1.5", token, 1).encode()
    with pytest.raises(WireError, match="keypoints"):
        decode(struct.pack(">4sBBI", b"PCAL", WIRE_VERSION, 1, len(head)) + head + png)
