"""Conventions of the ``posecal`` command line: --version, -v anywhere."""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
from pathlib import Path

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


def test_estimate_says_one_camera_has_no_rig(small_model_path, tmp_path, capsys):
    from estimator.sequence import write_sequence
    from estimator.synth import SynthSpec, synthesize

    write_sequence(tmp_path / "walk", synthesize(SynthSpec(n_cameras=1, n_frames=10, seed=4, image_size=(320, 240))))
    assert main(["estimate", str(tmp_path / "walk"), "--model", small_model_path, "--posture", "model",
                 "--out", str(tmp_path / "r.json")]) == 0
    printed = capsys.readouterr()
    assert "rig: one camera (c0), no rotations to give" in printed.out + printed.err
    assert "rotations from" not in printed.out + printed.err


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
    # The default segments the videos again with the model's feedback (§7.1) and estimates again
    fed = result["feedback"]
    assert fed["done"] and fed["priors"] >= 20 and fed["changed_pixels"] > 0, fed
    assert fed["note"] in result["notes"] and "estimated again" in fed["note"]
    off = tmp_path / "off.json"
    assert main(["estimate", str(folder), "--out", str(off), "--model", small_model_path, "--posture", "model",
                 "--warmup", "10", "--feedback", "off"]) == 0
    first = json.loads(off.read_text())
    assert "feedback" not in first and not any("feedback" in n for n in first["notes"])
    assert first["frames"] != result["frames"]  # the second estimate is of other silhouettes
    empty = tmp_path / "empty"
    empty.mkdir()
    assert main(["estimate", str(empty), "--model", small_model_path]) == 2  # neither videos nor a sequence
    assert "empty" in capsys.readouterr().err
    # A damaged video is bad input (exit 2, named), refused before the other cameras are segmented
    (folder / "c2.avi").write_bytes(b"")
    assert main(["estimate", str(folder), "--model", small_model_path, "--posture", "model"]) == 2
    assert "'c2.avi' cannot be decoded" in capsys.readouterr().err
    # A video found truncated while decoding (its header is fine) is left out, named; the others go on
    data = (folder / "c1.avi").read_bytes()
    (folder / "c2.avi").write_bytes(data[:len(data) // 8])  # a truncated copy: its header counts 36 frames
    out = tmp_path / "left_out.json"
    assert main(["estimate", str(folder), "--out", str(out), "--model", small_model_path, "--posture", "model",
                 "--warmup", "10", "--feedback", "off"]) == 0
    err = capsys.readouterr().err
    assert "warning: video c2.avi: only" in err and "of the 36 frames its header counts decode" in err, err
    left = json.loads(out.read_text())
    assert sorted(left["cameras"]) == ["c0", "c1"] and "c2" in left["sequence"]["left_out"], left["sequence"]
    assert any(n.startswith("c2: left out, video c2.avi: only") for n in left["notes"]), left["notes"]
    assert left["cameras"]["c0"]["azimuth_deg"] == first["cameras"]["c0"]["azimuth_deg"]  # nothing else lost
    # ... and when no video is left, the input is refused, every video named
    for name in ("c0", "c1"):
        (folder / f"{name}.avi").write_bytes(data[:len(data) // 8])
    assert main(["estimate", str(folder), "--model", small_model_path, "--posture", "model", "--warmup", "10"]) == 2
    err = capsys.readouterr().err
    assert all(f"video {n}.avi: only" in err for n in ("c0", "c1", "c2")), err


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
    assert [t.secret for t in s.api_tokens()] == [b"a" * 32]
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


# ------------------------------------------------- exit codes: 0 done, 1 could not be done, 2 usage or input
# Covered elsewhere: selfcal (tests/test_selfcal_cli.py: 0, 1 planar motion and unreliable rigs, 2 bad
# tracks), refine 0 and 2 (tests/test_prior.py), estimate 0 and 2 and docs 0 and 2 (above), serve 2
# (above). synth has no computation that fails on valid input but the renderer itself (a traceback, 1).


def _posecal(*argv: str, timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "service.cli", *argv], capture_output=True, text=True,
                          timeout=timeout)


def _busy_port():
    """A socket listening on a free loopback port (keep it open while the port must stay taken)."""
    import socket

    sock = socket.socket()
    sock.bind(("127.0.0.1", 0))
    sock.listen()
    return sock


def test_synth_exit_codes(tmp_path, capsys):
    assert main(["synth", "--out", str(tmp_path / "s"), "--cameras", "1", "--frames", "2", "--size", "64,48"]) == 0
    assert main(["synth", "--out", str(tmp_path / "s2"), "--size", "8,8"]) == 2
    assert "--size" in capsys.readouterr().err


def test_estimate_and_refine_exit_1_when_nothing_can_be_estimated(small_model_path, tmp_path, capsys):
    """A sequence folder that reads but whose silhouettes are all empty: no walker to estimate."""
    import numpy as np

    from estimator.sequence import write_sequence
    from estimator.synth import SynthSpec, synthesize

    seq = synthesize(SynthSpec(n_cameras=2, n_frames=6, seed=4, image_size=(160, 120)))
    seq.silhouettes = {c: [None if s is None else np.zeros_like(s) for s in v] for c, v in seq.silhouettes.items()}
    write_sequence(tmp_path / "empty", seq)
    for command in ("estimate", "refine"):
        out = tmp_path / f"{command}-out"
        assert main([command, str(tmp_path / "empty"), "--model", small_model_path, "--out", str(out)]) == 1
        err = capsys.readouterr().err
        assert f"posecal {command}: error:" in err and "no silhouettes" in err


def test_estimate_exports_and_exit_1_for_an_export_the_result_cannot_give(small_model_path, tmp_path, capsys):
    """--posture model: a rig from the viewpoints (no metric cameras). The result and the joints' exports
    are written, the calibration cannot be (exit 1, with the reason); a calibration file name of no
    known format is a usage error found before estimating (exit 2)."""
    import json

    from estimator.sequence import write_sequence
    from estimator.synth import SynthSpec, synthesize

    write_sequence(tmp_path / "walk", synthesize(SynthSpec(n_cameras=2, n_frames=10, seed=4, image_size=(320, 240))))
    base = ["estimate", str(tmp_path / "walk"), "--model", small_model_path, "--posture", "model",
            "--out", str(tmp_path / "r.json")]
    assert main(base + ["--export-calibration", str(tmp_path / "c.ini")]) == 2
    assert ".toml, .yaml, .yml, .json" in capsys.readouterr().err and not (tmp_path / "r.json").exists()
    code = main(base + ["--export-calibration", str(tmp_path / "c.toml"), "--export-trc", str(tmp_path / "w.trc"),
                        "--export-csv", str(tmp_path / "w.csv"), "--export-bvh", str(tmp_path / "w.bvh")])
    err = capsys.readouterr().err
    assert code == 1 and "--export-calibration" in err and "no metric cameras" in err, err
    assert json.loads((tmp_path / "r.json").read_text())["rig"]["source"] == "viewpoints"
    assert not (tmp_path / "c.toml").exists()
    assert (tmp_path / "w.trc").read_text().count("\n") == 5 + 10  # the model's joints3d, every frame
    assert (tmp_path / "w.csv").read_text().startswith("frame,time,head_x,")
    assert (tmp_path / "w.bvh").read_text().startswith("HIERARCHY")


def test_model_exit_codes(small_model_path, tmp_path, monkeypatch, capsys):
    import estimator.examples

    assert main(["model", "info", "--model", small_model_path]) == 0
    assert main(["model", "info", "--model", str(tmp_path / "missing.npz")]) == 2
    monkeypatch.delattr(estimator.examples, "render_examples")
    assert main(["model", "build", "--out", str(tmp_path / "m.npz"), "-q"]) == 1
    assert "not available" in capsys.readouterr().err


def test_docs_exit_1_when_the_documentation_is_not_installed(monkeypatch, capsys):
    monkeypatch.setattr("service.cli.docs.docs_dir", lambda: None)
    assert main(["docs"]) == 1 and "not installed" in capsys.readouterr().err


def test_capture_exit_codes(tmp_path):
    from service.server import free_port

    ok = _posecal("capture", "--source", "synthetic:seed=3,size=160x120", "--max-frames", "3", "--warmup", "2",
                  "--listen", f"tcp/127.0.0.1:{free_port()}")
    assert ok.returncode == 0, ok.stderr
    bad = _posecal("capture", "--source", str(tmp_path / "missing.mp4"), "--listen", f"tcp/127.0.0.1:{free_port()}")
    assert bad.returncode == 2 and "posecal capture: error:" in bad.stderr, bad.stderr
    with _busy_port() as sock:  # a valid endpoint the session cannot listen on
        failed = _posecal("capture", "--source", "synthetic:seed=3,size=160x120", "--max-frames", "3",
                          "--listen", f"tcp/127.0.0.1:{sock.getsockname()[1]}")
    assert failed.returncode == 1 and "posecal capture: error: zenoh:" in failed.stderr, failed.stderr


def test_serve_exit_codes(tmp_path, small_model_path):
    import signal
    import time

    from service.server import free_port

    common = ["--no-live", "--db", str(tmp_path / "j.db"), "--data-dir", str(tmp_path / "d"), "--model", small_model_path]
    with _busy_port() as sock:
        taken = _posecal("serve", "--port", str(sock.getsockname()[1]), *common)
    assert taken.returncode == 1 and "posecal serve: error: the server did not start" in taken.stderr, taken.stderr
    proc = subprocess.Popen([sys.executable, "-m", "service.cli", "serve", "--port", str(free_port()), *common],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 60
        for line in proc.stderr:  # uvicorn logs on stderr
            if "Application startup complete" in line or time.monotonic() > deadline:
                break
        proc.send_signal(signal.SIGINT)  # Ctrl-C: a clean stop
        assert proc.wait(timeout=60) == 0
    finally:
        if proc.poll() is None:
            proc.kill()


def test_demo_exit_codes(small_model_path, monkeypatch, capsys):
    import service.server

    assert main(["demo", "--cameras", "1"]) == 2

    def refuse(*args, **kwargs):
        raise RuntimeError("no room")

    monkeypatch.setattr(service.server, "BackgroundServer", refuse)
    made = []
    real_mkdtemp = tempfile.mkdtemp
    monkeypatch.setattr(tempfile, "mkdtemp", lambda **kw: made.append(real_mkdtemp(**kw)) or made[-1])
    assert main(["demo", "--model", small_model_path]) == 1
    assert "the service did not start: no room" in capsys.readouterr().err
    assert made and not Path(made[0]).exists()  # its empty working folder is not left behind


@pytest.mark.parametrize("where", ["process", "spawned worker"])
def test_a_native_crash_prints_the_python_stack(where):
    """A native library's crash (here a read of address 0) still says where it happened in
    Python, in the CLI's process and in the worker processes it spawns. Without
    report_native_crashes the process dies with no line on stderr."""
    crash = "import ctypes; ctypes.string_at(0)"
    if where == "spawned worker":
        crash = ("import ctypes, multiprocessing as mp\n"
                 "p = mp.get_context('spawn').Process(target=ctypes.string_at, args=(0,))\n"
                 "p.start(); p.join(60); print('worker exit', p.exitcode)")
    for setup, stack in (("", False), ("from service.cli import report_native_crashes; report_native_crashes()\n", True)):
        env = {k: v for k, v in os.environ.items() if k != "PYTHONFAULTHANDLER"}
        done = subprocess.run([sys.executable, "-c", setup + crash], capture_output=True, text=True, timeout=120,
                              cwd=Path(__file__).resolve().parents[1], env=env)
        if where == "process":
            assert done.returncode < 0, done  # killed by the signal
        else:
            assert "worker exit -" in done.stdout, done
        assert ("Fatal Python error" in done.stderr and "string_at" in done.stderr) == stack, done.stderr
