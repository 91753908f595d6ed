"""`temoto router`: a Zenoh router process that clients of the fleet talk through."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from temoto.cli.router import DEFAULT_LISTEN
from temoto.testing.inbox import Inbox
from temoto.transport import ZenohTransport
from temoto.transport.zenoh import DEFAULT_ROUTER_LISTEN, open_router

pytest.importorskip("zenoh", reason="the zenoh extra is not installed")

from _zenoh_helpers import WAIT_S, free_port, prefix, until_routed


def start_router(*args: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "temoto", "router", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def first_line(proc: subprocess.Popen[str]) -> str:
    """The first line of output, read on a thread so that a silent process fails in time."""
    lines: list[str] = []
    reader = threading.Thread(target=lambda: lines.append(proc.stdout.readline()))  # type: ignore[union-attr]
    reader.start()
    reader.join(WAIT_S * 2)
    if not (lines and lines[0]):
        err = proc.stderr.read() if proc.poll() is not None else "(still running)"  # type: ignore[union-attr]
        pytest.fail(f"temoto router announced nothing; stderr: {err}")
    return lines[0]


def test_the_cli_default_is_the_library_default() -> None:
    assert (DEFAULT_LISTEN,) == DEFAULT_ROUTER_LISTEN


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_clients_talk_through_the_router_which_a_signal_stops_with_exit_0(
    sig: signal.Signals,
) -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    proc = start_router("--listen", endpoint)
    try:
        line = first_line(proc)
        assert f"listening on {endpoint}" in line
        assert f"--fleet-url zenoh:{endpoint}" in line
        url = f"zenoh:{endpoint}?prefix={prefix()}"
        with ZenohTransport(url) as a, ZenohTransport(url) as b:
            inbox = Inbox()
            b.subscribe("VIA_ROUTER", inbox)
            until_routed(a, b)
            a.publish("VIA_ROUTER", b"hello")
            inbox.wait_for(1)
        os.kill(proc.pid, sig)
        _, err = proc.communicate(timeout=WAIT_S * 2)
        assert proc.returncode == 0, err
        assert f"{sig.name}: stopping" in err
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()


@pytest.mark.parametrize(
    ("args", "blamed"),
    [
        (["--listen", "7447"], "listen '7447' is not a Zenoh endpoint"),
        (["--config", "/nonexistent/zenoh.json5"], "/nonexistent/zenoh.json5"),
    ],
)
def test_bad_input_is_exit_2_with_one_line(args: list[str], blamed: str) -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "temoto", "router", *args],
        capture_output=True,
        text=True,
        timeout=WAIT_S * 2,
    )
    assert proc.returncode == 2
    assert blamed in proc.stderr
    assert proc.stderr.count("\n") == 1, proc.stderr


def test_an_address_in_use_is_exit_2_naming_it() -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    first = start_router("--listen", endpoint)
    try:
        first_line(first)
        proc = subprocess.run(
            [sys.executable, "-m", "temoto", "router", "--listen", endpoint],
            capture_output=True,
            text=True,
            timeout=WAIT_S * 2,
        )
        assert proc.returncode == 2
        assert f"cannot listen on {endpoint}" in proc.stderr
        assert "Address already in use" in proc.stderr
    finally:
        first.terminate()
        first.communicate(timeout=WAIT_S * 2)


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_serve_over_zenoh_exits_0_on_a_signal(sig: signal.Signals) -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_router((endpoint,))
    url = f"zenoh:{endpoint}?prefix={prefix()}"
    serve = subprocess.Popen(
        [sys.executable, "-m", "temoto", "serve", "--actor", "a", "--insecure", "--fleet-url", url],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert first_line(serve).strip() == "ready"
        os.kill(serve.pid, sig)
        _, err = serve.communicate(timeout=WAIT_S * 4)
        assert serve.returncode == 0, err
        assert "Traceback" not in err
    finally:
        if serve.poll() is None:
            serve.kill()
            serve.communicate()
        router.close()


def test_a_configuration_file_gives_the_router_its_endpoints(tmp_path: Path) -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    conf = tmp_path / "router.json5"
    conf.write_text(f'{{ listen: {{ endpoints: ["{endpoint}"] }} }}\n')
    proc = start_router("--config", str(conf))
    try:
        line = first_line(proc)
        assert f"the endpoints of {conf}" in line
        assert f"robots join with --fleet-url zenoh:{endpoint}" in line  # the file's endpoint
        url = f"zenoh:{endpoint}?prefix={prefix()}"
        with ZenohTransport(url) as a, ZenohTransport(url) as b:
            until_routed(a, b)
    finally:
        proc.terminate()
        proc.communicate(timeout=WAIT_S * 2)
    assert proc.returncode == 0
