"""Access (issue 20): bearer tokens on a real uvicorn server, and Zenoh user/password
authentication and TLS settings, checked on real Zenoh sessions on 127.0.0.1.

TLS: the ``cryptography`` package is not installed here, so no certificate is made and
TLS is tested as configuration (the keys Zenoh 1.x reads), not as a handshake."""

from __future__ import annotations

import json
import time

import pytest
import zenoh
from pydantic import ValidationError

from capture.wire import encode, silhouette_key
from capture.zconfig import ZenohAccess, build_config, config_from_args
from conftest_service import ServerThread, make_settings, wait_for
from service.server import free_port
from test_wire_hostile import BLOCK, _Agents, crops  # noqa: F401  (crops: a fixture)

TOKEN = "t0ken-for-the-lab-0123456789abcdef"
OTHER = "another-token-fedcba9876543210"


def test_rest_needs_a_bearer_token_when_one_is_set(tmp_path):
    token_file = tmp_path / "tokens"
    token_file.write_text(f"# lab tokens\n{OTHER}\n\n")
    settings = make_settings(tmp_path, job_workers=0, api_token=TOKEN, api_token_file=token_file)
    with ServerThread(settings) as srv:
        c = srv.client
        for path in ("/v1/jobs", "/v1/rigs", "/v1/jobs/nope", "/metrics"):
            r = c.get(path)
            assert r.status_code == 401 and r.headers["www-authenticate"] == "Bearer", (path, r.text)
            assert c.get(path, headers={"Authorization": "Bearer wrong"}).status_code == 401
            assert c.get(path, headers={"Authorization": TOKEN}).status_code == 401  # no scheme
        for token in (TOKEN, OTHER):
            auth = {"Authorization": f"Bearer {token}"}
            assert c.get("/v1/jobs", headers=auth).status_code == 200
            assert c.get("/v1/jobs/nope", headers=auth).status_code == 404
            assert c.get("/metrics", headers=auth).status_code == 200
        # Refused from the headers, before the body is read: nothing staged, no row.
        r = c.post("/v1/jobs", files={"files": ("walk.zip", b"PK" + b"\0" * 500_000, "application/zip")})
        assert r.status_code == 401
        assert list(settings.data_dir.iterdir()) == []
        assert c.post("/v1/jobs/nope/cancel").status_code == 401
        assert c.delete("/v1/jobs/nope").status_code == 401
        # /healthz and the API description stay open.
        assert c.get("/healthz").json()["status"] == "ok"
        spec = c.get("/openapi.json").json()
        assert "401" in spec["paths"]["/v1/jobs"]["get"]["responses"]
        assert spec["components"]["securitySchemes"]["HTTPBearer"]["scheme"] == "bearer"


def test_metrics_can_be_left_open_and_no_token_means_open(tmp_path):
    with ServerThread(make_settings(tmp_path, job_workers=0, api_token=TOKEN, metrics_open=True)) as srv:
        assert srv.client.get("/metrics").status_code == 200
        assert srv.client.get("/v1/jobs").status_code == 401
    with ServerThread(make_settings(tmp_path / "open", job_workers=0)) as srv:
        assert srv.client.get("/v1/jobs").status_code == 200


def test_bad_tokens_are_refused_at_start(tmp_path):
    with pytest.raises(ValueError, match="at least 16"):
        make_settings(tmp_path, api_token="short").api_tokens()
    empty = tmp_path / "empty"
    empty.write_text("# nothing\n")
    with pytest.raises(ValueError, match="holds no token"):
        make_settings(tmp_path, api_token_file=empty).api_tokens()
    with pytest.raises(ValueError, match="cannot read"):
        make_settings(tmp_path, api_token_file=tmp_path / "missing").api_tokens()


# --------------------------------------------------------------------------- zenoh


def _files(tmp_path) -> dict[str, str]:
    names = {"dictionary_file": "users.txt", "tls_root_ca": "ca.pem", "tls_certificate": "host.pem",
             "tls_private_key": "host-key.pem", "password_file": "password"}
    for key, name in names.items():
        (tmp_path / name).write_text("agent:secret\n" if key == "dictionary_file" else "secret\n")
    return {k: str(tmp_path / v) for k, v in names.items()}


def test_the_config_builder_writes_zenoh_1x_keys(tmp_path, monkeypatch):
    files = _files(tmp_path)
    access = ZenohAccess(user="agent", password_file=files["password_file"],
                         dictionary_file=files["dictionary_file"], tls_root_ca=files["tls_root_ca"],
                         tls_certificate=files["tls_certificate"], tls_private_key=files["tls_private_key"],
                         mtls=True)
    conf = build_config(listen=["tls/127.0.0.1:7447"], access=access)
    usrpwd = json.loads(conf.get_json("transport/auth/usrpwd"))
    assert usrpwd == {"user": "agent", "password": "secret", "dictionary_file": files["dictionary_file"]}
    tls = json.loads(conf.get_json("transport/link/tls"))
    assert tls["root_ca_certificate"] == files["tls_root_ca"] and tls["enable_mtls"] is True
    for side in ("listen", "connect"):
        assert tls[f"{side}_certificate"] == files["tls_certificate"]
        assert tls[f"{side}_private_key"] == files["tls_private_key"]
    assert json.loads(conf.get_json("listen/endpoints")) == ["tls/127.0.0.1:7447"]
    # Nothing set: nothing written (plain TCP, no authentication).
    plain = build_config(listen=["tcp/127.0.0.1:7447"], access=ZenohAccess())
    assert json.loads(plain.get_json("transport/auth/usrpwd"))["user"] is None
    # The agents and the router read the same settings from the environment.
    for key, value in (("USER", "agent"), ("PASSWORD", "pw-from-env"), ("TLS_ROOT_CA", files["tls_root_ca"])):
        monkeypatch.setenv(f"POSECAL_ZENOH_{key}", value)
    args = type("Args", (), dict(mode="peer", connect=["tls/127.0.0.1:7447"], listen=None, zenoh_config=None,
                                 multicast=False))()
    conf = config_from_args(args)
    assert json.loads(conf.get_json("transport/auth/usrpwd/password")) == "pw-from-env"
    assert json.loads(conf.get_json("transport/link/tls/root_ca_certificate")) == files["tls_root_ca"]


@pytest.mark.parametrize("fields, message", [
    ({"user": "agent"}, "both a user and a password"),
    ({"password": "x"}, "both a user and a password"),
    ({"tls_certificate": "/x.pem"}, "its private key"),
    ({"mtls": True}, "mutual TLS needs"),
])
def test_incomplete_access_settings_are_refused(fields, message):
    with pytest.raises(ValidationError, match=message):
        ZenohAccess(**fields)


def test_missing_access_files_are_named(tmp_path):
    with pytest.raises(ValueError, match="dictionary .*nope.txt does not exist"):
        build_config(access=ZenohAccess(dictionary_file=tmp_path / "nope.txt"))


def test_a_zenoh_listener_with_a_dictionary_admits_only_known_users(tmp_path):
    """A real session on 127.0.0.1 with user/password authentication: a peer with the
    right password is heard; a wrong password or none is refused."""
    users = tmp_path / "users.txt"
    users.write_text("agent:secret\nc1:other-secret\n")
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    got: list[str] = []
    service = ZenohAccess(dictionary_file=users)
    with zenoh.open(build_config(listen=[endpoint], access=service)) as listener:
        sub = listener.declare_subscriber("posecal/test/**", lambda s: got.append(str(s.key_expr)))

        def attempt(name: str, **credentials) -> None:
            with zenoh.open(build_config(connect=[endpoint], access=ZenohAccess(**credentials))) as peer:
                for _ in range(40):  # until heard, or 4 s for a peer that is refused
                    peer.put(f"posecal/test/{name}", b"x")
                    if f"posecal/test/{name}" in got:
                        return
                    time.sleep(0.1)

        attempt("good", user="agent", password="secret")
        attempt("wrong", user="agent", password="guess")
        attempt("none")
        attempt("good2", user="c1", password="other-secret")
        sub.undeclare()
    assert sorted(set(got)) == ["posecal/test/good", "posecal/test/good2"]


def test_the_service_hears_only_authenticated_agents(tmp_path, crops):  # noqa: F811
    """The service's own session with a user dictionary: silhouettes from an authenticated
    peer make a rig; the same from an unauthenticated one never arrive."""
    users = tmp_path / "users.txt"
    users.write_text("c-agents:lab-secret\n")
    settings = make_settings(tmp_path, live=True, job_workers=0, feedback=False, live_rig=False,
                             zenoh_access=ZenohAccess(dictionary_file=users))
    endpoint = settings.zenoh_listen
    with ServerThread(settings) as srv:
        for rig, access in (("stranger", ZenohAccess()),
                            ("lab", ZenohAccess(user="c-agents", password="lab-secret"))):
            with zenoh.open(build_config(connect=endpoint, access=access)) as session:
                agents = _Agents(session, {"c0": crops["c0"]}, rig=rig)
                for k in range(40):  # until heard, or about 4 s
                    session.put(silhouette_key(rig, "c0"), encode(agents.message("c0", k)),
                                congestion_control=BLOCK)
                    if srv.client.get(f"/v1/rigs/{rig}").status_code == 200:
                        break
                    time.sleep(0.1)
        rigs = wait_for(lambda: srv.client.get("/v1/rigs").json()["rigs"], timeout=5, what="the lab rig")
    assert [r["rig"] for r in rigs] == ["lab"]
