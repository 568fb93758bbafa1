"""Conventions of the ``posecal`` command line: --version, -v anywhere."""

from __future__ import annotations

import subprocess
import sys

import pytest

from service.cli import build_parser, main


def test_version():
    out = subprocess.run([sys.executable, "-m", "service.cli", "--version"], capture_output=True, text=True,
                         timeout=60)
    assert out.returncode == 0 and out.stdout.startswith("posecal ") and out.stdout.split()[1][0].isdigit()


@pytest.mark.parametrize("argv", [["-v", "synth", "--out", "x"], ["synth", "--out", "x", "-v"],
                                  ["synth", "-v", "--out", "x"]])
def test_verbose_before_or_after_the_sub_command(argv):
    args = build_parser().parse_args(argv)
    assert args.verbose is True and args.command == "synth"


def test_verbose_defaults_off_and_bad_arguments_exit_2(capsys):
    assert build_parser().parse_args(["synth", "--out", "x"]).verbose is False
    with pytest.raises(SystemExit) as exc:
        main(["synth", "--frames", "zero", "--out", "x"])
    assert exc.value.code == 2 and "--frames" in capsys.readouterr().err


def test_cache_dir_follows_posecal_cache_then_xdg(monkeypatch, tmp_path):
    from service.cli.model import cache_dir

    monkeypatch.delenv("POSECAL_CACHE", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert cache_dir() == tmp_path / "xdg" / "posecal"
    monkeypatch.setenv("XDG_CACHE_HOME", "relative/ignored")  # the spec: relative paths are invalid
    assert cache_dir().parts[-2:] == (".cache", "posecal") and cache_dir().is_absolute()
    monkeypatch.setenv("POSECAL_CACHE", str(tmp_path / "mine"))
    assert cache_dir() == tmp_path / "mine"


def test_estimate_writes_the_result_to_stdout_by_default(small_model_path, tmp_path, capsys):
    import json

    from estimator.sequence import write_sequence
    from estimator.synth import SynthSpec, synthesize

    write_sequence(tmp_path / "walk", synthesize(SynthSpec(n_cameras=2, n_frames=10, seed=4, image_size=(320, 240))))
    assert main(["estimate", str(tmp_path / "walk"), "--model", small_model_path, "--posture", "model"]) == 0
    out = capsys.readouterr()
    result = json.loads(out.out)  # standard output holds the result alone
    assert result["schema_version"] == 1 and len(result["frames"]) == 10
    assert "wrote standard output: 10 frames, 2 cameras" in out.err


def test_estimate_reads_a_folder_of_videos(small_model_path, tmp_path, capsys):
    """One video per camera: the walker is separated from the background, then estimated as a sequence."""
    import json

    import cv2

    from capture.synthetic import SyntheticSource

    folder = tmp_path / "videos"
    folder.mkdir()
    for cam, az in (("c0", 60.0), ("c1", 150.0)):
        src = SyntheticSource.from_spec(f"seed=3,azimuth={az},elevation=10,empty=12,pass=30,gap=0,size=320x240")
        writer = cv2.VideoWriter(str(folder / f"{cam}.avi"), cv2.VideoWriter_fourcc(*"MJPG"), 15, (320, 240))
        for i in range(36):
            writer.write(src.render(i).image)
        writer.release()
        src.close()
    out = tmp_path / "r.json"
    assert main(["estimate", str(folder), "--out", str(out), "--model", small_model_path, "--posture", "model",
                 "--warmup", "10"]) == 0
    result = json.loads(out.read_text())
    assert result["sequence"]["frames"] == 36 and result["sequence"]["videos"] == ["c0.avi", "c1.avi"]
    assert result["cameras"]["c0"]["decoded_frames"] == 36
    walking = [f for f in result["frames"][12:] if f["seen_by"] == ["c0", "c1"]]
    assert len(walking) >= 20
    for cam, az in (("c0", 60.0), ("c1", 150.0)):
        assert abs((result["cameras"][cam]["azimuth_deg"] - az + 180) % 360 - 180) < 25, result["cameras"]
    empty = tmp_path / "empty"
    empty.mkdir()
    assert main(["estimate", str(empty), "--model", small_model_path]) == 2  # neither videos nor a sequence
    assert "empty" in capsys.readouterr().err


def test_serve_refuses_to_listen_beyond_loopback_without_tokens(tmp_path, capsys):
    from service.cli.serve import check_exposure, settings_from_args

    parser = build_parser()

    def settings(*extra):
        args = parser.parse_args(["serve", "--db", str(tmp_path / "j.db"), "--data-dir", str(tmp_path / "d"),
                                  *extra])
        return args, settings_from_args(args)

    args, s = settings("--host", "0.0.0.0")
    with pytest.raises(Exception, match="beyond this machine without API tokens"):
        check_exposure(args.host, s, args.insecure)
    args, s = settings("--host", "0.0.0.0", "--insecure")
    check_exposure(args.host, s, args.insecure)  # told to
    for host in ("127.0.0.1", "localhost", "::1"):
        check_exposure(host, s, False)  # loopback is fine without tokens
    tokens = tmp_path / "tokens"
    tokens.write_text("# lab\n" + "a" * 32 + "\n")
    args, s = settings("--host", "0.0.0.0", "--api-token-file", str(tokens))
    check_exposure(args.host, s, args.insecure)
    assert s.api_tokens() == (b"a" * 32,)
    tokens.write_text("# nothing\n")
    with pytest.raises(Exception, match="holds no token"):
        check_exposure("127.0.0.1", s, False)
    assert main(["serve", "--host", "0.0.0.0", "--db", str(tmp_path / "j.db")]) == 2
    assert "--insecure" in capsys.readouterr().err


def test_docs_lists_and_prints_the_pages_shipped(capsys):
    assert main(["docs"]) == 0
    listing = capsys.readouterr().out
    assert "formats" in listing and "service" in listing
    assert main(["docs", "FORMATS"]) == 0
    assert capsys.readouterr().out.startswith("# posecal formats and conventions")
    assert main(["docs", "nope"]) == 2 and "formats" in capsys.readouterr().err
