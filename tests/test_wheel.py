"""The installed wheel works on its own, without any extra.

The wheel is built from a copy of the source (``pip wheel --no-deps``; the pure build, to spare
the machine a compile) and installed in a fresh virtual environment without extras (its
required dependencies come from the package index or pip's cache). Then, from a folder outside
the repository: every sub-command's ``--help``, ``temoto demo 1``, the commands whose extras are
missing (one line naming the extra), and the README's quick start after ``temoto examples .``.
No traceback anywhere.

Slow (a minute or two: the build, the venv, the installs); run once, in the pure pass of
``make test`` (it builds the pure wheel; the compiled pass skips it).
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys
import venv
from collections.abc import Iterator
from pathlib import Path

import pytest

from temoto.cli import _parser

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"

pytestmark = [
    pytest.mark.slow,
    pytest.mark.timeout(900),
    pytest.mark.skipif(
        os.environ.get("TEMOTO_REQUIRE_EXTENSIONS", "") not in ("", "0"),
        reason="builds and tests the pure wheel: runs in the pure pass of `make test`",
    ),
]

SOURCES = ("temoto", "examples", "hw_profiles", "pyproject.toml", "setup.py", "README.md")
SOURCES_TOO = ("_temoto_entry.py", "LICENSE", "MANIFEST.in")


def _env(home: Path) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    env["TEMOTO_NO_EXTENSIONS"] = "1"  # the pure build: no compile, and no warning about it
    env["HOME"] = str(home)  # nothing of the user's (state files, keys) is seen
    env["XDG_CACHE_HOME"] = os.environ.get("XDG_CACHE_HOME", str(Path.home() / ".cache"))
    return env


@pytest.fixture(scope="module")
def installed(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, dict]:
    tmp = tmp_path_factory.mktemp("wheel")
    src = tmp / "src"
    src.mkdir()
    ignore = shutil.ignore_patterns("__pycache__", "*.so", "*.c", "*.egg-info")
    for name in (*SOURCES, *SOURCES_TOO):
        path = ROOT / name
        if path.is_dir():
            shutil.copytree(path, src / name, ignore=ignore)
        elif path.exists():
            shutil.copy2(path, src / name)
    home = tmp / "home"
    home.mkdir()
    env = _env(home)
    dist = tmp / "dist"
    subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(dist), str(src)],
        check=True,
        cwd=tmp,
        env=env,
        timeout=600,
    )
    (wheel,) = dist.glob("temoto-*.whl")
    env_dir = tmp / "venv"
    venv.EnvBuilder(with_pip=True, system_site_packages=False).create(env_dir)
    py = env_dir / "bin" / "python"
    subprocess.run(
        [str(py), "-m", "pip", "install", "-q", "--disable-pip-version-check", str(wheel)],
        check=True,
        env=env,
        timeout=600,
    )
    work = tmp / "work"  # outside the repository, and not the source copy
    work.mkdir()
    return env_dir / "bin", work, env


def _run(bin_dir: Path, work: Path, env: dict, *args: str, timeout: float = 120) -> tuple:
    done = subprocess.run(
        [str(bin_dir / args[0]), *args[1:]],
        capture_output=True,
        text=True,
        cwd=work,
        env=env,
        timeout=timeout,
        check=False,
    )
    return done.returncode, done.stdout, done.stderr


def _commands(parser: argparse.ArgumentParser, prefix: tuple[str, ...] = ()) -> Iterator[tuple]:
    """Every sub-command path of the parser (``("graph", "dot")``, ...)."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield (*prefix, name)
                yield from _commands(sub, (*prefix, name))


def test_every_sub_commands_help_works_without_extras(installed: tuple) -> None:
    bin_dir, work, env = installed
    commands = [(), *list(_commands(_parser()))]
    assert len(commands) > 12
    for path in commands:
        code, out, err = _run(bin_dir, work, env, "temoto", *path, "--help")
        assert code == 0, (path, err)
        assert "Traceback" not in out + err, path
        assert "usage: temoto" in out, path


def test_demo_1_runs_from_the_wheel(installed: tuple) -> None:
    bin_dir, work, env = installed
    code, out, err = _run(bin_dir, work, env, "temoto", "demo", "1", "--speed", "5", timeout=300)
    assert "Traceback" not in out + err
    assert code == 0, err[-2000:]


@pytest.mark.parametrize(
    ("args", "extra"),
    [
        (("demo", "2", "--speed", "5"), "can"),
        (("sim", "quad"), "mavlink"),
        (("sim", "--profile", "hw_profiles/sim_arm.yaml"), "dynamixel"),
    ],
)
def test_a_command_whose_extra_is_missing_names_it_in_one_line(
    installed: tuple, args: tuple[str, ...], extra: str
) -> None:
    bin_dir, work, env = installed
    if "--profile" in args and not (work / "hw_profiles").is_dir():
        _run(bin_dir, work, env, "temoto", "examples", ".")
    code, out, err = _run(bin_dir, work, env, "temoto", *args, timeout=300)
    assert "Traceback" not in out + err
    assert code == 2, err
    lines = [line for line in err.splitlines() if line.startswith("temoto: error:")]
    assert len(lines) == 1, err
    assert f"pip install 'temoto[{extra}]'" in lines[0]


def _quick_start() -> tuple[str, str]:
    """The README's quick start: its first Python block and the `temoto run` command after it."""
    text = README.read_text(encoding="utf-8")
    section = text[text.index("## Quick start") :]
    python = re.search(r"```python\n(.*?)```", section, re.S)
    shell = re.search(r"```sh\n(.*?temoto run .*?)```", section, re.S)
    assert python is not None
    assert shell is not None
    return python.group(1), shell.group(1)


def test_the_readmes_quick_start_runs_from_the_wheel(installed: tuple) -> None:
    bin_dir, work, env = installed
    if not (work / "examples").is_dir():
        code, out, err = _run(bin_dir, work, env, "temoto", "examples", ".")
        assert code == 0, err
    python, shell = _quick_start()
    code, out, err = _run(bin_dir, work, env, "python", "-c", python)
    assert "Traceback" not in out + err
    assert code == 0, err
    assert "Result.TRUE" in out
    for line in shell.strip().splitlines():
        if line.startswith("#") or not line.strip():
            continue
        words = line.split()
        words[0] = words[0].rsplit("/", 1)[-1]  # `.venv/bin/temoto`: the venv's temoto
        code, out, err = _run(bin_dir, work, env, *words)
        assert "Traceback" not in out + err
        assert code == 0, (line, err)
