"""deploy/: the compose file and the systemd units start posecal commands that exist, with
settings the service accepts (no Docker daemon is needed: each command is parsed by
posecal's own parser and each POSECAL_* variable validated by its settings)."""

import os
import re
import shlex
from pathlib import Path

import pytest
import yaml

from capture.agent import AgentSettings
from service.cli import build_parser
from service.settings import Settings

DEPLOY = Path(__file__).resolve().parent.parent / "deploy"
TOKEN = "0123456789abcdef0123456789abcdef"


@pytest.fixture(scope="module")
def compose() -> dict:
    text = (DEPLOY / "compose.yaml").read_text()
    # ${VAR:?message} and ${VAR:-default}: what `docker compose` substitutes from deploy/.env
    text = re.sub(r"\$\{POSECAL_API_TOKEN:\?[^}]*\}", TOKEN, text)
    assert "${" not in text, "an unsubstituted variable in compose.yaml"
    return yaml.safe_load(text)


def _posecal_services(compose: dict) -> dict[str, dict]:
    return {name: s for name, s in compose["services"].items() if s.get("image") == "posecal:latest"}


def _settings_from(env: dict[str, str], monkeypatch, cls=Settings):
    for key in [k for k in os.environ if k.startswith("POSECAL_")]:
        monkeypatch.delenv(key)
    for key, value in env.items():
        monkeypatch.setenv(key, str(value))
    return cls()


def test_the_compose_file_holds_the_whole_system(compose):
    services = compose["services"]
    ours = _posecal_services(compose)
    roles = {name: s["command"][0] for name, s in ours.items()}
    assert sorted(set(roles.values())) == ["capture", "router", "serve", "worker"]
    assert "postgres" in services and services["postgres"]["image"].startswith("postgres:")
    serves = [n for n, r in roles.items() if r == "serve"]
    assert len(serves) >= 2  # replicas
    ids = [s["command"][s["command"].index("--replica-id") + 1] for n, s in ours.items() if roles[n] == "serve"]
    assert len(set(ids)) == len(ids), "replica ids must be unique"
    for s in services.values():
        for port in s.get("ports", []):
            assert port.startswith("127.0.0.1:"), f"published beyond loopback: {port}"


def test_every_compose_command_parses(compose):
    parser = build_parser()
    for name, s in _posecal_services(compose).items():
        args = parser.parse_args(s["command"])  # exits (SystemExit) on an unknown flag
        assert args.command == s["command"][0], name


def test_the_replicas_settings_are_valid_and_shared(compose, monkeypatch):
    ours = _posecal_services(compose)
    seen = []
    for name, s in ours.items():
        if s["command"][0] != "serve":
            continue
        fields = set(Settings.model_fields)
        for key in s["environment"]:
            assert key.startswith("POSECAL_") and key[8:].lower() in fields, (name, key)
        settings = _settings_from(s["environment"], monkeypatch)
        assert settings.db_url.startswith("postgresql+psycopg://")
        assert settings.api_tokens()  # listening beyond loopback needs tokens
        seen.append((settings.db_url, settings.data_dir, tuple(settings.zenoh_connect)))
    assert len(set(seen)) == 1, "replicas must share one database, one upload directory and one router"
    worker = next(s for s in ours.values() if s["command"][0] == "worker")
    cmd = worker["command"]
    assert cmd[cmd.index("--db") + 1] == seen[0][0]
    assert Path(cmd[cmd.index("--data-dir") + 1]) == seen[0][1]


def test_the_agents_form_one_rig_through_the_router(compose):
    parser = build_parser()
    agents = [parser.parse_args(s["command"]) for s in _posecal_services(compose).values()
              if s["command"][0] == "capture"]
    assert len(agents) >= 2
    assert len({a.rig for a in agents}) == 1 and len({a.camera for a in agents}) == len(agents)
    assert all(a.connect == ["tcp/router:7447"] and a.mode == "client" for a in agents)


def _env_file(name: str) -> dict[str, str]:
    lines = (DEPLOY / name).read_text().splitlines()
    return dict(x.split("=", 1) for x in lines if x and not x.startswith("#") and "=" in x)


def _unit_command(unit: str, env_file: str) -> list[str]:
    text = (DEPLOY / unit).read_text()
    line = next(x for x in text.splitlines() if x.startswith("ExecStart="))
    # Environment= lines of the unit, then its EnvironmentFile (which overrides them)
    env = dict(x.split("=", 2)[1:] for x in text.splitlines() if x.startswith("Environment="))
    env.update(_env_file(env_file))
    line = re.sub(r"\$\{(\w+)\}", lambda m: env[m.group(1)], line.split("=", 1)[1])
    line = line.replace("%i", "c0").replace("%H", "host")
    argv = shlex.split(line)
    assert argv[0].endswith("/posecal")
    return argv[1:]


@pytest.mark.parametrize("unit, env_file", [("posecal-serve.service", "posecal.env"),
                                            ("posecal-worker@.service", "posecal.env"),
                                            ("posecal-capture@.service", "capture-c0.env")])
def test_the_systemd_units_start_commands_that_exist(unit, env_file, monkeypatch):
    argv = _unit_command(unit, env_file)
    args = build_parser().parse_args(argv)
    assert args.command == argv[0]
    env = _env_file(env_file)
    if env_file == "posecal.env":
        env.pop("POSECAL_HTTP_HOST"), env.pop("POSECAL_HTTP_PORT")  # the unit's command line
        _settings_from(env, monkeypatch)
    else:
        _settings_from({k: v for k, v in env.items() if not k.startswith("POSECAL_ZENOH_")}, monkeypatch,
                       AgentSettings)
