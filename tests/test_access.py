"""Access (issue 20): bearer tokens and their scopes on a real uvicorn server; Zenoh
user/password authentication, TLS, mutual TLS and access rules on real Zenoh sessions
on 127.0.0.1, with certificates made by ``deploy/make-lab-ca.sh`` (openssl).

Refusals are shown by order, not by time where a link exists: a forged message is sent
before each genuine one on the same link, so once the genuine ones arrive the forged
ones would have too. A peer that cannot connect at all is given a bounded number of
attempts (as long as an admitted one needs many times over)."""

from __future__ import annotations

import json
import subprocess
import time
from pathlib import Path

import pytest
import zenoh
from pydantic import ValidationError

from capture.wire import encode, estimate_key, feedback_key, silhouette_key
from capture.zconfig import ZenohAccess, access_rules, build_config, config_from_args
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


# --------------------------------------------------------------------------- scoped tokens

READ = "read-only-token-0123456789abcdef"
SUBMIT = "submit-token-0123456789abcdef00"
ADMIN = "admin-token-0123456789abcdef0000"


@pytest.fixture(scope="module")
def walk_zip(tmp_path_factory) -> bytes:
    """A small synthetic 2-camera sequence, zipped as a user would upload it."""
    from conftest_service import sequence_zip, write_walk

    return sequence_zip(write_walk(tmp_path_factory.mktemp("walk") / "walk", n_frames=20, seed=2))


def test_scoped_tokens_get_403_for_what_their_scope_does_not_allow(tmp_path, walk_zip):
    """read: GET only; submit: POST jobs and read; admin (or no scope): cancel and delete too.
    A missing scope is 403 with the reason, from the headers (an upload is not read);
    an unknown token is still 401."""
    token_file = tmp_path / "tokens"
    token_file.write_text(f"# lab tokens\n{READ} read\n{SUBMIT} submit\n{ADMIN}\n{OTHER} read,admin\n")
    settings = make_settings(tmp_path, job_workers=0, api_token_file=token_file)
    with ServerThread(settings) as srv:
        c = srv.client

        def auth(token: str) -> dict[str, str]:
            return {"Authorization": f"Bearer {token}"}

        def upload():
            return {"files": ("walk.zip", walk_zip, "application/zip")}

        for token in (READ, SUBMIT, ADMIN, OTHER):
            for path in ("/v1/jobs", "/v1/rigs", "/metrics"):
                assert c.get(path, headers=auth(token)).status_code == 200, (token, path)
        # read: no submitting, cancelling or deleting; refused before the upload is read.
        r = c.post("/v1/jobs", files=upload(), headers=auth(READ))
        assert r.status_code == 403 and "'submit' scope" in r.json()["detail"], r.text
        assert 'error="insufficient_scope"' in r.headers["www-authenticate"]
        assert list(settings.data_dir.iterdir()) == []
        # submit: a job is accepted ...
        r = c.post("/v1/jobs", files=upload(), headers=auth(SUBMIT))
        assert r.status_code == 202, r.text
        job = r.json()["id"]
        assert c.get(f"/v1/jobs/{job}", headers=auth(READ)).json()["state"] == "queued"
        # ... but only admin may cancel or delete it.
        for token in (READ, SUBMIT):
            r = c.post(f"/v1/jobs/{job}/cancel", headers=auth(token))
            assert r.status_code == 403 and "'admin' scope" in r.json()["detail"], r.text
            assert c.delete(f"/v1/jobs/{job}", headers=auth(token)).status_code == 403
        assert c.get(f"/v1/jobs/{job}", headers=auth(READ)).json()["state"] == "queued"
        assert c.post(f"/v1/jobs/{job}/cancel", headers=auth(ADMIN)).json()["state"] == "cancelled"
        assert c.delete(f"/v1/jobs/{job}", headers=auth(OTHER)).status_code == 204
        # admin (a bare token) submits too; unknown tokens stay 401, /healthz open.
        assert c.post("/v1/jobs", files=upload(), headers=auth(ADMIN)).status_code == 202
        assert c.post("/v1/jobs/x/cancel", headers=auth("not-a-token-0123456789")).status_code == 401
        assert c.get("/healthz").status_code == 200
        spec = c.get("/openapi.json").json()
        assert "403" in spec["paths"]["/v1/jobs/{job_id}"]["delete"]["responses"]


def test_token_scopes_are_read_from_the_file(tmp_path):
    token_file = tmp_path / "tokens"
    token_file.write_text(f"{READ} read\n{SUBMIT}\tsubmit\n{ADMIN}\n{OTHER} read, admin\n")
    tokens = {t.secret.decode(): t.scopes for t in make_settings(tmp_path, api_token=TOKEN,
                                                                 api_token_file=token_file).api_tokens()}
    assert tokens == {READ: {"read"}, SUBMIT: {"read", "submit"}, ADMIN: {"read", "submit", "admin"},
                      OTHER: {"read", "submit", "admin"}, TOKEN: {"read", "submit", "admin"}}
    token_file.write_text(f"# lab\n{READ} read\n{SUBMIT} write\n")
    with pytest.raises(ValueError, match="line 3: unknown API token scope 'write'"):
        make_settings(tmp_path, api_token_file=token_file).api_tokens()


# --------------------------------------------------------------------------- the lab CA

MAKE_CA = Path(__file__).resolve().parents[1] / "deploy" / "make-lab-ca.sh"


def make_ca(directory: Path, *agents: str, options: tuple[str, ...] = ()) -> subprocess.CompletedProcess:
    """Run ``deploy/make-lab-ca.sh [options] DIR [AGENT ...]``."""
    return subprocess.run(["sh", str(MAKE_CA), *options, str(directory), *agents],
                          capture_output=True, text=True, timeout=120)


def _openssl(*args: str) -> str:
    return subprocess.run(["openssl", *args], capture_output=True, text=True, check=True, timeout=60).stdout


@pytest.fixture(scope="module")
def lab_ca(tmp_path_factory) -> Path:
    """A lab CA with the service's certificate (localhost, 127.0.0.1) and agents lab-c0, lab-c1."""
    directory = tmp_path_factory.mktemp("tls") / "lab"
    done = make_ca(directory, "lab-c0", "lab-c1")
    assert done.returncode == 0, done.stderr
    return directory


def test_the_lab_ca_script_makes_and_keeps_certificates(tmp_path):
    lab = tmp_path / "lab"
    done = make_ca(lab, "lab-c0", options=("--hosts", "svc.lab,10.0.0.5"))
    assert done.returncode == 0, done.stderr
    names = {p.name for p in lab.iterdir()}
    assert names == {"ca.pem", "ca-key.pem", "service.pem", "service-key.pem", "lab-c0.pem", "lab-c0-key.pem"}
    assert all((lab / n).stat().st_mode & 0o077 == 0 for n in names if n.endswith("-key.pem"))
    for name in ("service", "lab-c0"):
        assert "OK" in _openssl("verify", "-CAfile", str(lab / "ca.pem"), str(lab / f"{name}.pem"))
    service = _openssl("x509", "-in", str(lab / "service.pem"), "-noout", "-subject", "-ext",
                       "subjectAltName,extendedKeyUsage")
    assert "CN = service" in service and "DNS:svc.lab, IP Address:10.0.0.5" in service
    assert "Server Authentication" in service
    agent = _openssl("x509", "-in", str(lab / "lab-c0.pem"), "-noout", "-subject", "-ext", "extendedKeyUsage")
    assert "CN = lab-c0" in agent and "Client Authentication" in agent and "Server" not in agent
    # Again, with one more agent: the CA and the certificates that are still right are kept.
    before = {n: (lab / n).read_bytes() for n in names}
    done = make_ca(lab, "lab-c0", "lab-c1", options=("--hosts", "svc.lab,10.0.0.5"))
    assert done.returncode == 0, done.stderr
    assert {n: (lab / n).read_bytes() for n in names} == before
    assert "OK" in _openssl("verify", "-CAfile", str(lab / "ca.pem"), str(lab / "lab-c1.pem"))
    # Other host names: only the service's certificate is re-issued.
    assert make_ca(lab, options=("--hosts", "svc2.lab")).returncode == 0
    assert (lab / "service.pem").read_bytes() != before["service.pem"]
    assert (lab / "ca.pem").read_bytes() == before["ca.pem"]
    # The CA is replaced only when told; half a CA is refused.
    assert make_ca(lab, "lab-c0", options=("--new-ca",)).returncode == 0
    assert (lab / "ca.pem").read_bytes() != before["ca.pem"]
    assert "OK" in _openssl("verify", "-CAfile", str(lab / "ca.pem"), str(lab / "lab-c0.pem"))
    (lab / "ca-key.pem").unlink()
    done = make_ca(lab)
    assert done.returncode != 0 and "half a CA" in done.stderr
    assert make_ca(tmp_path / "x", "bad name").returncode != 0


# --------------------------------------------------------------------------- zenoh TLS and rules


def _tls(ca: Path, name: str | None = None, **fields) -> ZenohAccess:
    """Access with the lab CA and, given a name, that certificate and key."""
    own = {} if name is None else {"tls_certificate": ca / f"{name}.pem", "tls_private_key": ca / f"{name}-key.pem"}
    return ZenohAccess(tls_root_ca=ca / "ca.pem", **own, **fields)


def _heard_from(connect: str, access: ZenohAccess, heard: list[str], key: str, *, mode: str = "peer",
                attempts: int = 40) -> bool:
    """Open a session to ``connect`` and put ``key`` until the listener has heard it, or
    ``attempts`` times (0.1 s apart); whether it was heard. A client that cannot connect
    fails to open: not heard."""
    try:
        session = zenoh.open(build_config(mode=mode, connect=[connect], access=access))
    except zenoh.ZError as exc:
        assert mode == "client" and "Unable to connect" in str(exc), exc
        return False
    with session as peer:
        for _ in range(attempts):
            peer.put(key, b"x")
            if key in heard:
                return True
            time.sleep(0.1)
    return False


def test_zenoh_tls_with_the_lab_certificates(lab_ca, tmp_path):
    """A tls/ listener with the service's certificate: an agent that trusts the lab CA is heard
    (by address and by name); a peer that does not, or that speaks plain TCP, is not."""
    port = free_port()
    heard: list[str] = []
    with zenoh.open(build_config(listen=[f"tls/127.0.0.1:{port}"], access=_tls(lab_ca, "service"))) as service:
        sub = service.declare_subscriber("posecal/**", lambda s: heard.append(str(s.key_expr)))
        for host in ("127.0.0.1", "localhost"):
            assert _heard_from(f"tls/{host}:{port}", _tls(lab_ca), heard, f"posecal/{host}/c0/silhouette")
        other = tmp_path / "other"
        assert make_ca(other).returncode == 0
        assert not _heard_from(f"tls/127.0.0.1:{port}", _tls(other), heard, "posecal/other-ca/c0/silhouette")
        assert not _heard_from(f"tls/127.0.0.1:{port}", ZenohAccess(), heard, "posecal/no-ca/c0/silhouette")
        assert not _heard_from(f"tcp/127.0.0.1:{port}", ZenohAccess(), heard, "posecal/plain/c0/silhouette")
        sub.undeclare()
    assert sorted(set(heard)) == ["posecal/127.0.0.1/c0/silhouette", "posecal/localhost/c0/silhouette"]


def test_mutual_tls_refuses_a_peer_without_a_client_certificate(lab_ca, tmp_path):
    port = free_port()
    endpoint = f"tls/127.0.0.1:{port}"
    heard: list[str] = []
    with zenoh.open(build_config(listen=[endpoint], access=_tls(lab_ca, "service", mtls=True))) as service:
        sub = service.declare_subscriber("posecal/**", lambda s: heard.append(str(s.key_expr)))
        assert _heard_from(endpoint, _tls(lab_ca, "lab-c0", mtls=True), heard, "posecal/lab/c0/silhouette")
        assert not _heard_from(endpoint, _tls(lab_ca), heard, "posecal/lab/c1/silhouette")  # CA only
        other = tmp_path / "other"
        assert make_ca(other, "lab-c1").returncode == 0  # a certificate, from another CA
        assert not _heard_from(endpoint, _tls(other, "lab-c1", mtls=True), heard, "posecal/lab/c1/silhouette")
        sub.undeclare()
    assert sorted(set(heard)) == ["posecal/lab/c0/silhouette"]


def test_access_rules_are_generated_from_the_cameras():
    acl = access_rules({"lab-c0": "lab/c0"}, ["service"], by_certificate=True, by_user=False)
    assert acl["enabled"] is True and acl["default_permission"] == "deny"
    rules = {r["id"]: r for r in acl["rules"]}
    assert rules["lab-c0-publish"] == {"id": "lab-c0-publish", "permission": "allow", "flows": ["ingress"],
                                       "messages": ["put"], "key_exprs": ["posecal/lab/c0/silhouette"]}
    assert rules["lab-c0-subscribe"]["key_exprs"] == rules["lab-c0-receive"]["key_exprs"] == \
        ["posecal/lab/c0/feedback"]
    assert {"id": "lab-c0", "cert_common_names": ["lab-c0"]} in acl["subjects"]
    assert {"id": "trusted", "subjects": ["service"], "rules": ["everything-in", "everything-out"]} in acl["policies"]
    # Names are matched by certificate and/or user name: one of them must be on.
    with pytest.raises(ValidationError, match="certificate .mtls. or their user name"):
        ZenohAccess(agents={"lab-c0": "lab/c0"})
    with pytest.raises(ValidationError, match="'rig/camera'"):
        ZenohAccess(dictionary_file="/x", agents={"lab-c0": "lab"})
    with pytest.raises(ValidationError, match="both an agent and trusted"):
        ZenohAccess(dictionary_file="/x", agents={"lab-c0": "lab/c0"}, trusted=["lab-c0"])


def test_the_shipped_access_rules_example_is_what_the_code_makes(monkeypatch, tmp_path):
    """deploy/zenoh-access.example.json5 is the config its header's variables generate."""
    example = Path(__file__).resolve().parents[1] / "deploy" / "zenoh-access.example.json5"
    shipped = json.loads(zenoh.Config.from_file(str(example)).get_json("access_control"))
    users = tmp_path / "users.txt"
    users.write_text("lab-c0:x\n")
    for key, value in (("AGENTS", '{"lab-c0": "lab/c0", "lab-c1": "lab/c1"}'), ("TRUSTED", '["service"]'),
                       ("DICTIONARY_FILE", str(users)), ("MTLS", "true"), ("TLS_ROOT_CA", str(users)),
                       ("TLS_CERTIFICATE", str(users)), ("TLS_PRIVATE_KEY", str(users))):
        monkeypatch.setenv(f"POSECAL_ZENOH_{key}", value)
    made = json.loads(build_config(listen=["tls/127.0.0.1:7447"], access=ZenohAccess()).get_json("access_control"))
    assert shipped == made


def test_an_agent_may_put_only_its_camera_and_read_only_its_priors(lab_ca):
    """Rules on the listener, agents named by their certificates (mutual TLS): lab-c0's
    silhouettes under c1's key and its subscription to c1's priors reach nothing; its own do."""
    endpoint = f"tls/127.0.0.1:{free_port()}"
    rules = {"agents": {"lab-c0": "lab/c0", "lab-c1": "lab/c1"}}
    heard: list[str] = []
    got: list[str] = []
    with zenoh.open(build_config(listen=[endpoint], access=_tls(lab_ca, "service", mtls=True, **rules))) as service:
        sub = service.declare_subscriber(silhouette_key("*", "*"), lambda s: heard.append(str(s.key_expr)))
        priors = {cam: service.declare_publisher(feedback_key("lab", cam)) for cam in ("c1", "c0")}
        estimates = service.declare_publisher(estimate_key("lab"))
        with zenoh.open(build_config(connect=[endpoint], access=_tls(lab_ca, "lab-c0", mtls=True))) as agent:
            for key in (feedback_key("lab", "c1"), estimate_key("lab"), feedback_key("lab", "c0")):
                agent.declare_subscriber(key, lambda s: got.append(str(s.key_expr)))
            forged, own = (agent.declare_publisher(silhouette_key("lab", cam)) for cam in ("c1", "c0"))
            for _ in range(100):  # forged before own, on the same links: order, not time
                forged.put(b"forged")
                own.put(b"own")
                estimates.put(b"{}")
                for pub in priors.values():  # c1's before c0's
                    pub.put(b"prior")
                if heard.count(silhouette_key("lab", "c0")) >= 5 and got.count(feedback_key("lab", "c0")) >= 5:
                    break
                time.sleep(0.05)
        sub.undeclare()
    assert set(heard) == {silhouette_key("lab", "c0")}
    assert set(got) == {feedback_key("lab", "c0")}


def test_the_service_hears_an_agent_only_as_its_own_camera(tmp_path, crops):  # noqa: F811
    """The service's own session with rules from POSECAL_ZENOH_AGENTS (user names): the
    agent of c0 publishing c1's silhouettes too leaves the rig with c0 alone; c1's agent
    is heard as c1."""
    users = tmp_path / "users.txt"
    users.write_text("lab-c0:secret-c0\nlab-c1:secret-c1\n")
    access = ZenohAccess(dictionary_file=users, agents={"lab-c0": "lab/c0", "lab-c1": "lab/c1"})
    settings = make_settings(tmp_path, live=True, job_workers=0, feedback=False, live_rig=False,
                             zenoh_access=access)
    with ServerThread(settings) as srv:

        def frames(cam: str) -> int:
            return srv.rig("lab").get("cameras", {}).get(cam, {}).get("frames", 0)

        agent = ZenohAccess(user="lab-c0", password="secret-c0")  # a client, as deploy/ runs agents
        with zenoh.open(build_config(mode="client", connect=settings.zenoh_listen, access=agent)) as session:
            agents = _Agents(session, crops, rig="lab")  # c0 and c1 from lab-c0's session
            for k in range(200):  # c1's forged frame before each of c0's
                for cam in ("c1", "c0"):
                    agents.pubs[cam].put(encode(agents.message(cam, k)))
                if frames("c0") >= 10:
                    break
                time.sleep(0.05)
        rig = srv.rig("lab")
        assert list(rig["cameras"]) == ["c0"] and rig["cameras"]["c0"]["frames"] >= 10
        with zenoh.open(build_config(connect=settings.zenoh_listen,
                                     access=ZenohAccess(user="lab-c1", password="secret-c1"))) as session:
            agents = _Agents(session, {"c1": crops["c1"]}, rig="lab")
            for k in range(200):
                agents.pubs["c1"].put(encode(agents.message("c1", k)))
                if frames("c1") >= 3:
                    break
                time.sleep(0.05)
        assert sorted(srv.rig("lab")["cameras"]) == ["c0", "c1"]


def test_rules_on_a_router_let_the_trusted_service_through(lab_ca):
    """A router with the rules (mutual TLS): the service, trusted by its certificate, hears
    lab-c0 (a client) as c0 only and sends it its priors; a peer without a certificate gets
    nothing through."""
    endpoint = f"tls/127.0.0.1:{free_port()}"
    rules = {"agents": {"lab-c0": "lab/c0"}, "trusted": ["service"]}
    heard: list[str] = []
    got: list[str] = []
    router_conf = build_config(mode="router", listen=[endpoint], access=_tls(lab_ca, "service", mtls=True, **rules))
    service_conf = build_config(connect=[endpoint], access=_tls(lab_ca, "service", mtls=True))
    agent_conf = build_config(mode="client", connect=[endpoint], access=_tls(lab_ca, "lab-c0", mtls=True))
    with zenoh.open(router_conf), zenoh.open(service_conf) as service:
        sub = service.declare_subscriber(silhouette_key("*", "*"), lambda s: heard.append(str(s.key_expr)))
        prior = service.declare_publisher(feedback_key("lab", "c0"))
        with zenoh.open(agent_conf) as agent:
            agent.declare_subscriber(feedback_key("lab", "c0"), lambda s: got.append(str(s.key_expr)))
            forged, own = (agent.declare_publisher(silhouette_key("lab", cam)) for cam in ("c1", "c0"))
            for _ in range(100):
                forged.put(b"forged")
                own.put(b"own")
                prior.put(b"prior")
                if heard.count(silhouette_key("lab", "c0")) >= 5 and got:
                    break
                time.sleep(0.05)
        for mode in ("client", "peer"):
            assert not _heard_from(endpoint, _tls(lab_ca), heard, silhouette_key("stranger", "c0"), mode=mode)
        sub.undeclare()
    assert set(heard) == {silhouette_key("lab", "c0")} and got
