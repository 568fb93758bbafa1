"""estimator/ stays pure: importing it loads no web, network or Rerun module."""

import subprocess
import sys


def test_estimator_imports_no_service_stack():
    code = (
        "import sys, estimator, estimator.render, estimator.synth\n"
        "bad = [m for m in ('fastapi', 'uvicorn', 'zenoh', 'rerun', 'starlette', 'service', 'capture') if m in sys.modules]\n"
        "print(','.join(bad))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "", f"estimator imported {out.stdout.strip()}"
