"""The result models of service/schemas.py describe what the code writes (and OpenAPI publishes them)."""

from __future__ import annotations

import dataclasses

import pytest
from pydantic import BaseModel

from service.schemas import LiveEstimate, Result


def _undeclared(model: BaseModel, path: str = "") -> list[str]:
    """Keys a validated model kept as extras (not declared), recursively."""
    out = [f"{path}.{k}" for k in (model.model_extra or {})]
    for name in type(model).model_fields:
        out += _walk(getattr(model, name), f"{path}.{name}")
    return out


def _walk(value, path: str) -> list[str]:
    if isinstance(value, BaseModel):
        return _undeclared(value, path)
    if isinstance(value, dict):
        return [p for k, v in value.items() for p in _walk(v, f"{path}.{k}")]
    if isinstance(value, list):
        return [p for v in value[:3] for p in _walk(v, f"{path}[]")]
    return []


@pytest.fixture(scope="module")
def batch(small_model) -> dict:
    """A real result with every optional part: mNBP postures, self-calibrated rig, segments."""
    from estimator.mnbp import measure_postures
    from estimator.pipeline import tracks_from_sequence
    from estimator.synth import SynthSpec, synthesize
    from estimator.windows import segment_walk

    seq = synthesize(SynthSpec(n_cameras=2, n_frames=16, seed=2, image_size=(320, 240)))
    from estimator.mnbp import MNBPConfig
    from estimator.rig import RigConfig

    walk = segment_walk(tracks_from_sequence(seq), small_model, length=16, posture=MNBPConfig(), rig=RigConfig())
    return walk.to_result()


def test_a_batch_result_is_a_result_with_nothing_undeclared(batch):
    model = Result.model_validate(batch)
    assert _undeclared(model) == []
    assert model.rig is not None and model.frames[0].phase_posterior is not None
    assert model.segments and model.windows


def test_a_live_result_is_a_live_estimate(batch):
    live = {k: v for k, v in batch.items() if k not in ("rig", "body", "segments", "windows")}
    live["frames"] = [{k: v for k, v in f.items() if k not in ("person_joints3d", "model_joints2d", "segment")}
                      for f in live["frames"]]
    live.update(rig="lab", window={"seq": 3, "first_index": 0, "last_index": 15, "frames": 16, "cameras": ["c0"]},
                smoothed={"c0": {"azimuth_deg": 10.0}}, latency_ms={"estimate": 30.0, "last_frame_to_result": 41.0},
                published_ns=1)
    assert _undeclared(LiveEstimate.model_validate(live)) == []


def test_openapi_publishes_the_schemas_and_the_error_statuses():
    from service.app import create_app

    spec = create_app().openapi()
    est = spec["paths"]["/v1/rigs/{rig}/estimate"]["get"]["responses"]
    assert est["200"]["content"]["application/json"]["schema"]["$ref"].endswith("/LiveEstimate")
    assert est["404"]["content"]["application/json"]["example"]["detail"]
    res = spec["paths"]["/v1/jobs/{job_id}/result"]["get"]["responses"]
    assert res["200"]["content"]["application/json"]["schema"]["$ref"].endswith("/Result")
    assert {"404", "409"} <= set(res)
    assert {"400", "413", "415", "422"} <= set(spec["paths"]["/v1/jobs"]["post"]["responses"])
    cal = spec["paths"]["/v1/rigs/{rig}/calibration"]["get"]["responses"]
    assert cal["200"]["content"]["application/json"]["schema"]["$ref"].endswith("/LiveCalibration")


def test_json_safe_makes_strict_json_of_numbers_rows_and_numpy_scalars():
    """NaN and inf become null wherever they are (rows of floats take a fast path), tuples become
    lists, numpy scalars Python numbers; the result is what json.dumps(allow_nan=False) accepts."""
    import json

    import numpy as np

    from service.worker import json_safe

    value = {"row": [1.0, float("nan"), 2.5], "fine": (2.0, 3.0), "mixed": [np.float32(1.5), np.inf, 3],
             "nested": [[1.0, -np.inf], [0.5, 0.25]], "scalar": np.float64(np.nan), "text": ["a", 1.0]}
    safe = json_safe(value)
    assert safe == {"row": [1.0, None, 2.5], "fine": [2.0, 3.0], "mixed": [1.5, None, 3],
                    "nested": [[1.0, None], [0.5, 0.25]], "scalar": None, "text": ["a", 1.0]}
    assert type(safe["fine"]) is list and safe["nested"][1] is not value["nested"][1]  # copies, not aliases
    json.dumps(safe, allow_nan=False)
