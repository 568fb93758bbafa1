"""Appearance model: EM clustering, cluster means, matching, artifact, cache, CLI."""

from __future__ import annotations

import argparse
import json

import numpy as np
import pytest
from sklearn.mixture import GaussianMixture

from estimator import _cluster
from estimator._stick_examples import grid_examples
from estimator.appearance import (
    FORMAT_VERSION,
    AppearanceModel,
    build_model,
    choose_n_clusters,
    default_model,
    joint_features,
    load_model,
    save_model,
    within_scatter_curve,
)
from estimator.registration import register

N_CLUSTERS = 24


@pytest.fixture(scope="module")
def examples():
    # 20 phases x 24 azimuths x 3 elevations, 2 body styles: 2,880 examples.
    return grid_examples(azimuth_step=15.0, elevations=np.array([-15.0, 5.0, 25.0]), n_styles=2)


@pytest.fixture(scope="module")
def model(examples):
    return build_model(examples, n_clusters=N_CLUSTERS, rng=7)


def test_every_example_belongs_to_one_cluster(examples, model):
    n = len(examples)
    assert model.n_examples == n
    assert sorted(model.member_index.tolist()) == list(range(n))  # a permutation
    counts = np.diff(model.member_offsets)
    assert counts.sum() == n and (counts > 0).all()
    labels = model.labels
    assert labels.shape == (n,) and labels.min() >= 0 and labels.max() < model.n_clusters
    # Member arrays are the examples' own values, in cluster order.
    np.testing.assert_array_equal(model.member_phase, examples.phase[model.member_index])
    np.testing.assert_array_equal(model.member_azimuth_deg, examples.azimuth_deg[model.member_index])
    m = model.members(3)
    assert (labels[m["index"]] == 3).all()
    with pytest.raises(ValueError, match="cluster index"):
        model.members(model.n_clusters)


def test_means_are_member_averages(examples, model):
    reg, _ = register(examples.silhouettes, size=model.size)
    assert model.means.shape == (model.n_clusters, *model.size)
    assert model.means.min() >= 0 and model.means.max() <= 1
    for k in (0, model.n_clusters // 2, model.n_clusters - 1):
        idx = model.members(k)["index"]
        np.testing.assert_allclose(model.means[k], reg[idx].mean(0), atol=1e-6)


def test_same_seed_same_model(examples, model):
    again = build_model(examples, n_clusters=N_CLUSTERS, rng=7)
    for name in ("means", "gmm_weights", "gmm_means", "gmm_covariances", "member_offsets",
                 "member_index"):
        np.testing.assert_array_equal(getattr(again, name), getattr(model, name), err_msg=name)
    assert again.params == model.params


def test_gmm_parameters_are_a_valid_mixture(model):
    assert np.isclose(model.gmm_weights.sum(), 1.0)
    assert np.all(np.linalg.eigvalsh(model.gmm_covariances) > 0)
    assert model.provenance["em"]["n_iter"] >= 1


def test_em_matches_scikit_learn(examples):
    """The batched EM does scikit-learn's full-covariance updates (eqs. 3–5)."""
    reg, tf = register(examples.silhouettes)
    x = joint_features(examples.joints2d, tf, size=(64, 48), height_fraction=0.8)[::3]
    k, reg_covar = 12, 1e-4
    labels = np.arange(len(x)) % k  # any hard start
    start = _cluster.fit_gmm(x, k, rng=np.random.default_rng(0), tol=0, max_iter=0,
                             reg_covar=reg_covar, init_labels=labels)
    ours = _cluster.fit_gmm(x, k, rng=np.random.default_rng(0), tol=0, max_iter=4,
                            reg_covar=reg_covar, init_labels=labels)
    with pytest.warns(Warning):  # sklearn: "did not converge" after 4 iterations
        sk = GaussianMixture(k, covariance_type="full", reg_covar=reg_covar, max_iter=4, tol=0,
                             weights_init=start.weights, means_init=start.means,
                             precisions_init=np.linalg.inv(start.covariances)).fit(x)
    np.testing.assert_allclose(ours.weights, sk.weights_, atol=1e-9)
    np.testing.assert_allclose(ours.means, sk.means_, atol=1e-9)
    np.testing.assert_allclose(ours.covariances, sk.covariances_, atol=1e-9)
    np.testing.assert_array_equal(ours.labels, sk.predict(x))


def test_matching_recovers_viewpoint_and_phase(model):
    """Fresh silhouettes (other style, off-grid views) match clusters of similar views."""
    from estimator._stick_examples import make_examples, style_table

    g = np.random.default_rng(11)
    n = 60
    ph, az, el = g.uniform(0, 1, n), g.uniform(0, 360, n), g.uniform(-15, 25, n)
    ex = make_examples(ph, az, el, np.full(n, 3), styles=style_table(4, rng=99), px_per_m=90.0,
                       crop=(200, 140))
    best, d = model.match(ex.silhouettes)
    assert d.shape == (n, model.n_clusters) and best.shape == (n,)
    assert (best == d.argmin(1)).all()
    vp = model.cluster_viewpoint[best]
    # Front/back ambiguity (the same silhouette from az and 180 - az): take the closer.
    err = np.minimum(_angdiff(vp[:, 0], az), _angdiff(vp[:, 0], 180.0 - az))
    assert np.median(err) < 35.0
    assert np.median(np.abs(vp[:, 1] - el)) < 15.0


def _angdiff(a, b):
    return np.abs((a - b + 180.0) % 360.0 - 180.0)


def test_match_handles_empty_silhouettes(model):
    sil = np.zeros((2, 80, 60), np.uint8)
    sil[1, 10:70, 25:35] = 255
    best, d = model.match(sil)
    assert best[0] == -1 and np.isinf(d[0]).all()
    assert best[1] >= 0 and np.isfinite(d[1]).all()


def test_save_load_roundtrip(tmp_path, model):
    path = save_model(model, tmp_path / "m.npz")
    back = load_model(path)
    assert isinstance(back, AppearanceModel)
    np.testing.assert_allclose(back.means, model.means, atol=1e-3)  # float16 on disk
    for name in ("gmm_means", "gmm_covariances", "member_offsets", "member_index", "member_phase",
                 "member_azimuth_deg", "member_elevation_deg", "member_style"):
        np.testing.assert_array_equal(getattr(back, name), getattr(model, name), err_msg=name)
    assert back.params == model.params and back.version == model.version
    assert back.info()["clusters"] == model.n_clusters
    json.dumps(back.info())  # JSON-able
    assert path.stat().st_size < 2e6


def test_load_rejects_other_files(tmp_path, model):
    other = tmp_path / "other.npz"
    np.savez(other, a=np.zeros(3))
    with pytest.raises(ValueError, match="not a posecal appearance model"):
        load_model(other)
    path = save_model(model, tmp_path / "m.npz")
    with np.load(path) as z:
        arrays = dict(z)
    arrays["format_version"] = np.array(999)
    np.savez(tmp_path / "future.npz", **arrays)
    with pytest.raises(ValueError, match="format version 999"):
        load_model(tmp_path / "future.npz")
    (tmp_path / "broken.npz").write_bytes(b"PK\x03\x04 truncated")
    with pytest.raises(ValueError):
        load_model(tmp_path / "broken.npz")


def test_default_model_builds_once_then_loads(tmp_path, examples):
    calls = []

    def make():
        calls.append(1)
        return examples

    key = {"source": "test", "version": "1"}
    m1 = default_model(tmp_path, make_examples=make, key=key, n_clusters=8)
    m2 = default_model(tmp_path, make_examples=make, key=key, n_clusters=8)
    assert len(calls) == 1 and m1.n_clusters == m2.n_clusters == 8
    assert len(list(tmp_path.glob(f"appearance-v{FORMAT_VERSION}-*.npz"))) == 1
    np.testing.assert_array_equal(m1.member_index, m2.member_index)


def test_build_validates_input(examples):
    with pytest.raises(ValueError, match="at least n_clusters"):
        build_model(examples, n_clusters=len(examples) + 1)
    with pytest.raises(ValueError, match="Examples"):
        build_model(examples.silhouettes)
    with pytest.raises(ValueError, match="rng"):
        build_model(examples, n_clusters=4, rng="seed")


def test_within_scatter_curve_and_choice(examples):
    ks = [2, 8, 24, 48]
    tr = within_scatter_curve(examples, ks, rng=0)
    assert tr.shape == (4,) and (np.diff(tr) < 0).all()
    assert choose_n_clusters(ks, tr) in ks
    ks2 = np.arange(10, 310, 10)
    assert choose_n_clusters(ks2, 1.0 / ks2) < 100  # knee of a 1/k curve is early
    with pytest.raises(ValueError):
        choose_n_clusters([1, 2], [3, 4])


def test_cli_build_and_info(tmp_path, monkeypatch, examples, capsys):
    from service.cli import model as cli_model

    monkeypatch.setenv("POSECAL_CACHE", str(tmp_path / "cache"))
    monkeypatch.setattr(cli_model._Progress, "render_examples", lambda self: examples)
    parser = argparse.ArgumentParser()
    cli_model.register(parser.add_subparsers(dest="command"))
    out = tmp_path / "m.npz"
    args = parser.parse_args(["model", "build", "--out", str(out), "--clusters", "6", "-q"])
    assert args.func(args) == 0 and out.exists()
    capsys.readouterr()
    args = parser.parse_args(["model", "info", "--model", str(out), "--json"])
    assert args.func(args) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["clusters"] == 6 and info["examples"] == len(examples)
    assert info["params"]["n_clusters"] == 6
    args = parser.parse_args(["model", "info"])
    from service.cli import CliError

    with pytest.raises(CliError, match="posecal model build"):
        args.func(args)


def test_rendered_model_matches_fresh_walkers(small_model):
    """The real body (conftest's small rendered model): fresh walkers of other
    sizes and gaits, off-grid views, match clusters near their viewpoint and phase
    (up to the silhouette's twin: phase + 1/2, azimuth 180 - az)."""
    from estimator.camera import Camera
    from estimator.gait import GaitStyle, load_gait
    from estimator.render import Renderer
    from estimator.skeleton import BodyShape, forward_kinematics

    g = np.random.default_rng(5)
    n = 40
    ph, az, el = g.uniform(0, 1, n), g.uniform(0, 360, n), g.uniform(-10, 30, n)
    shape, style = BodyShape.random(g), GaitStyle.random(g)
    poses = forward_kinematics(load_gait().angles(ph, style), shape)
    sils = []
    with Renderer(shape, image_size=(120, 200)) as r:
        for i in range(n):
            cam = Camera(az[i], el[i], distance=8.0, image_size=(120, 200), focal_px=150 * 8.0 / shape.height,
                         target=tuple(poses[i, :13].mean(0)))
            sils.append(r.render(poses[i], cam)[0])
    best, _ = small_model.match(np.stack(sils))
    vp = small_model.cluster_viewpoint[best]
    cph = small_model.cluster_phase[best]
    err_az = np.minimum(_angdiff(vp[:, 0], az), _angdiff(vp[:, 0], 180.0 - az))
    raw = _angdiff(vp[:, 0], az) / 180 + np.abs((cph - ph + 0.5) % 1 - 0.5) / 0.5
    twin = _angdiff(vp[:, 0], 180 - az) / 180 + np.abs((cph - ph) % 1 - 0.5) / 0.5
    assert np.median(err_az) < 20.0
    assert np.median(np.minimum(raw, twin)) < 0.35


def test_cluster_summaries_are_circular(model):
    import dataclasses

    n = model.n_examples
    az = np.where(np.arange(n) % 2 == 0, 355.0, 5.0)  # every cluster straddles 0 deg
    ph = np.where(np.arange(n) % 2 == 0, 0.95, 0.05)
    m = dataclasses.replace(model, member_azimuth_deg=az, member_phase=ph,
                            member_elevation_deg=np.full(n, 12.5))
    vp = m.cluster_viewpoint
    assert np.all(_angdiff(vp[:, 0], 0.0) < 1.0)
    np.testing.assert_allclose(vp[:, 1], 12.5)
    assert np.all(np.abs((m.cluster_phase + 0.5) % 1.0 - 0.5) < 0.01)


def test_get_default_model_uses_the_cache(tmp_path, monkeypatch, examples):
    from service.cli import model as cli_model

    monkeypatch.setenv("POSECAL_CACHE", str(tmp_path))
    calls = []

    def fake_render(self):
        calls.append(1)
        return examples

    monkeypatch.setattr(cli_model._Progress, "render_examples", fake_render)
    m1 = cli_model.get_default_model(progress=False)
    assert cli_model.default_model_path().exists()
    assert cli_model.default_model_path().parent == tmp_path
    m2 = cli_model.get_default_model(progress=False)
    assert len(calls) == 1 and m1.n_clusters == m2.n_clusters == 100
