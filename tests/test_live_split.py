"""A live window's cameras split over worker processes (service.worker.estimate_window):
the same estimate as in one process, each camera kept in its process, a dead worker
costing one window at most. Real worker processes (spawned, holding the model)."""

import json
import os
import signal
import time

import numpy as np
import pytest

from estimator.damage import damage_sequence
from estimator.matchcache import MatchCache
from estimator.pipeline import estimate_walk, tracks_from_sequence
from estimator.sequence import Sequence
from estimator.synth import SynthSpec, synthesize
from estimator.windows import ViewpointTrack, earlier_azimuths, own_azimuth, window_tracks
from service.worker import (WindowBefore, camera_shares, estimate_window, json_safe, make_pinned_pools,
                            match_cache_stats, warm_window)
from test_pipeline import contested_shadow_walk, out_of_step_walk


@pytest.fixture(scope="module")
def pools(small_model_path):
    p = make_pinned_pools(2, small_model_path)
    yield p
    p.terminate()


def _same(a: dict, b: dict) -> None:
    assert json.dumps(a, sort_keys=True) == json.dumps(b, sort_keys=True)


def test_a_window_split_over_two_processes_is_the_one_process_estimate(pools, small_model, mocap_dir):
    """The hardest window of tests/test_pipeline.py: a shadow cut at the feet puts two of three
    cameras' motion cues on the wrong side, and the other cameras' phase settles them: that
    step and the phase-given re-vote cross the processes; the estimate is the same."""
    seq, tracks = contested_shadow_walk(mocap_dir)
    indices = list(range(100, 130))
    sizes = {c: seq.image_size for c in tracks}

    alone = estimate_walk(tracks, small_model)
    expected = json_safe(alone.to_result(first_index=100))
    for frame, index in zip(expected["frames"], indices):
        frame["index"] = index
    result, bundle, seconds, est = estimate_window(pools, "rig", tracks, indices, sizes, bundle_from=0)

    assert len(set().union(*camera_shares(list(tracks), "rig", 2).values())) == 3
    assert sum("settled by the other cameras" in n for c in result["cameras"].values() for n in c["notes"]) == 2
    _same(result, expected)
    np.testing.assert_array_equal(est.states, alone.states)
    assert all(est.tracks[c].cut.sum() == alone.tracks[c].cut.sum() > 0 for c in tracks)  # the cleaned tracks
    assert sorted(bundle.clouds) == sorted(tracks) and all(len(v) for v in bundle.clouds.values())
    assert seconds > 0


def test_the_side_earlier_windows_found_crosses_the_processes(pools, small_model):
    """A camera held on the side its earlier windows found (its mirror observed where it is
    observed, the side settled where the HMM joins them): the same as in one process."""
    tracks = out_of_step_walk(7)
    earlier = {"c0": 150.0, "c1": 110.0, "c2": 250.0}
    expected = json_safe(estimate_walk(tracks, small_model, earlier=earlier).to_result())
    for frame, index in zip(expected["frames"], range(24)):
        frame["index"] = index
    result, *_ = estimate_window(pools, "held", tracks, list(range(24)), {c: (320, 240) for c in tracks},
                                 earlier=earlier)
    assert result["cameras"]["c0"]["flip"] == "earlier"
    _same(result, expected)


def test_the_smoothing_is_fed_the_side_each_window_found_by_itself():
    """A window held on its earlier side is smoothed as what it found by itself, so that a smoothed
    viewpoint on the wrong side is still outvoted (the hold never feeds on itself)."""
    track = ViewpointTrack(threshold_deg=30.0, confirm=3, settle=3)
    for k in range(3):
        track.update(150.0, 10.0, k)
    assert own_azimuth(150.0, "earlier") == 30.0 and own_azimuth(150.0, "motion") == 150.0
    assert own_azimuth(None, "earlier") is None
    assert earlier_azimuths({"c0": track}, 2) == {"c0": 150.0} and earlier_azimuths({"c0": track}, 4) is None
    assert earlier_azimuths({"c0": track}, 0) is None
    outlier = ViewpointTrack(threshold_deg=30.0, confirm=3, settle=3)
    for k, az in enumerate((150.0, 152.0, 30.0, 151.0)):  # an outlier among the last two: no earlier side
        outlier.update(az, 10.0, k)
    assert earlier_azimuths({"c0": outlier}, 2) is None and earlier_azimuths({"c0": outlier}, 1) is not None
    outlier.update(149.0, 10.0, 4)
    assert earlier_azimuths({"c0": outlier}, 2) == {"c0": outlier.value[0]}
    for k in range(3, 6):
        state = track.update(own_azimuth(150.0, "earlier"), 10.0, k)
    assert abs(state["azimuth_deg"] - 30.0) < 1e-6 and len(state["changes"]) == 1


def test_each_camera_stays_in_its_process_so_overlapping_windows_are_matched_once(pools, small_model):
    """Live windows overlap by half: the second window's shared frames are in the match cache of
    the process that saw them, because each camera goes to the same process."""
    seq = synthesize(SynthSpec(n_cameras=4, n_frames=30, seed=5, image_size=(320, 240)))
    full = tracks_from_sequence(seq)
    sizes = {c: seq.image_size for c in full}
    shares = camera_shares(sorted(full), "walk", 2)
    assert sorted(len(s) for s in shares.values()) == [2, 2]  # dealt evenly
    assert camera_shares(sorted(full), "walk", 2) == shares  # and the same every window

    before = _stats(pools)["hits"]
    estimate_window(pools, "walk", window_tracks(full, 0, 20), list(range(20)), sizes)
    within = _stats(pools)["hits"] - before  # the shadow test's scores, found again by the match
    second, *_ = estimate_window(pools, "walk", window_tracks(full, 10, 30), list(range(10, 30)), sizes)
    assert _stats(pools)["hits"] - before - within >= within + 4 * 10  # and every camera's frames 10-19, in its own process
    alone = estimate_walk(window_tracks(full, 10, 30), small_model)
    assert [f["phase"] for f in second["frames"]] == pytest.approx(alone.phase.tolist())


def _stats(pools) -> dict[str, int]:
    """The match caches' hits and misses, summed over the processes."""
    each = [pools.submit_to(k, match_cache_stats).result(timeout=30) for k in range(len(pools))]
    return {key: sum(e[key] for e in each) for key in each[0]}


def _delta(pools, before: dict[str, int]) -> dict[str, int]:
    return {k: v - before[k] for k, v in _stats(pools).items()}


def test_frames_looked_at_before_their_window_closes_leave_it_little_to_do_and_change_nothing(pools, small_model):
    """The live service sends a window's frames to its processes as they come
    (``warm_every``), with the window before's viewpoints and phase: when the window
    closes, its silhouettes are registered in the process that estimates their camera,
    most of what it derives from them is there, and the estimate is the one computed
    without (the same windows in one process with a cache of its own, nothing looked at
    early, for comparison)."""
    seq = synthesize(SynthSpec(n_cameras=4, n_frames=30, seed=7, image_size=(320, 240)))
    full = tracks_from_sequence(seq)
    sizes = {c: seq.image_size for c in full}
    cache = MatchCache(max_entries=1280)
    estimate_walk(window_tracks(full, 0, 20), small_model, cache=cache)
    misses, derived = cache.misses, cache.derived_misses
    alone = estimate_walk(window_tracks(full, 10, 30), small_model, cache=cache)
    misses, derived = cache.misses - misses, cache.derived_misses - derived

    _, _, _, first = estimate_window(pools, "warm", window_tracks(full, 0, 20), list(range(20)), sizes)
    for a in range(20, 29, 3):  # frames 20-28 in looks of 3, as the service sends them; 29 closes
        frames = list(range(a, a + 3))
        assert warm_window(pools, "warm", window_tracks(full, a, a + 3), frames,
                           WindowBefore.of(1, list(range(20)), first)).result(timeout=60) == 4 * 3
    start = _stats(pools)
    result, *_ = estimate_window(pools, "warm", window_tracks(full, 10, 30), list(range(10, 30)), sizes)
    done = _delta(pools, start)
    assert done["misses"] <= misses - 4 * 9  # frames 20-28 of every camera were registered before
    assert done["derived_misses"] < 0.5 * derived
    assert [f["phase"] for f in result["frames"]] == pytest.approx(alone.phase.tolist())
    assert {c: v["azimuth_deg"] for c, v in result["cameras"].items()} == pytest.approx(
        {c: v.viewpoint.azimuth_deg for c, v in alone.cameras.items()}, abs=1e-3)  # the result's rounding


def test_a_dead_worker_costs_a_window_at_most(pools, small_model):
    """A worker process killed (out of memory, a crash): the window it held may fail, the next
    one is estimated on a fresh process, and the other process's state is untouched."""
    seq = synthesize(SynthSpec(n_cameras=2, n_frames=20, seed=9, image_size=(320, 240)))
    tracks = tracks_from_sequence(seq)
    sizes = {c: seq.image_size for c in tracks}
    victim = pools.pools[1].pids[0]
    os.kill(victim, signal.SIGKILL)
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline:  # the pool notices the death
        try:
            os.kill(victim, 0)
        except ProcessLookupError:
            break
        time.sleep(0.05)
    outcomes = []
    for _ in range(3):
        try:
            outcomes.append(estimate_window(pools, "dead", tracks, list(range(20)), sizes)[0])
        except Exception as exc:  # noqa: BLE001 - the window that hit the dead worker
            outcomes.append(exc)
    assert not isinstance(outcomes[-1], Exception) and sum(isinstance(o, Exception) for o in outcomes) <= 1
    assert victim not in pools.pids and len(pools.pids) == 2
    expected = json_safe(estimate_walk(tracks, small_model).to_result())
    assert [f["phase"] for f in outcomes[-1]["frames"]] == [f["phase"] for f in expected["frames"]]


def test_an_early_look_is_done_once_when_its_last_process_is():
    """The processes' futures of one early look joined (their callbacks run in several pools'
    threads): done once, when the last is, with the first error or a cancellation (a pool
    terminated at stop), so that the service's count of looks in flight comes down."""
    from concurrent.futures import CancelledError, Future

    from service.worker import _all_of

    a, b = Future(), Future()
    both = _all_of([a, b])
    a.set_result(2)
    assert not both.done()
    b.set_result(3)
    assert both.result() == 5
    a, b = Future(), Future()
    both = _all_of([a, b])
    assert a.cancel()
    b.set_exception(ValueError("worker died"))
    assert isinstance(both.exception(), CancelledError)
    a, b = Future(), Future()
    both = _all_of([a, b])
    b.set_exception(ValueError("worker died"))
    a.set_result(1)
    assert isinstance(both.exception(), ValueError)
    assert _all_of([]).result() == 0


def test_a_walker_behind_a_wall_split_over_two_processes_is_the_one_process_estimate(pools, small_model):
    """Cameras whose walker is hidden below (estimator.occlusion) are matched against a cut model that
    each process builds for itself, without the match cache; their tracks carry the hidden share
    across the processes. Split, and looked at early, the window is the one-process estimate."""
    seq = synthesize(SynthSpec(n_cameras=3, n_frames=20, seed=5, azimuths=(60.0, 150.0, 250.0),
                               elevations=(10.0, 10.0, 5.0), image_size=(320, 240)))
    walled = damage_sequence(seq.silhouettes, "low_wall", seed=0)
    tracks = tracks_from_sequence(Sequence(seq.fps, seq.cameras, seq.image_size, walled, seq.truth))
    sizes = {c: seq.image_size for c in tracks}
    alone = estimate_walk(tracks, small_model)
    expected = json_safe(alone.to_result(first_index=0))
    warm_window(pools, "wall", window_tracks(tracks, 0, 10), list(range(10))).result(timeout=60)
    result, _, _, est = estimate_window(pools, "wall", tracks, list(range(20)), sizes)
    _same(result, expected)
    for cam, c in result["cameras"].items():
        assert any("hidden by something in front" in n for n in c["notes"]), cam
        assert est.tracks[cam].hidden.max() == alone.tracks[cam].hidden.max() > 0.1
