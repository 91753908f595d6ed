"""`temoto keys new|add|revoke|list`, identity and roster files, joining a fleet with them."""

from __future__ import annotations

import argparse
import os
import stat
from pathlib import Path

import pytest

from temoto.cli import main
from temoto.cli.fleet import fleet_key
from temoto.errors import ConfigError
from temoto.transport.identity import (
    Credentials,
    Identity,
    Policy,
    Roster,
    RosterError,
    public_key_text,
)


def keys(*argv: str) -> int:
    return main(["keys", *argv])


def test_new_add_list_revoke(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    roster = tmp_path / "fleet.roster"
    assert keys("new", "robot_1", "-o", str(tmp_path / "r1.id"), "--roster", str(roster)) == 0
    line = capsys.readouterr().out.strip()
    me = Identity.load(tmp_path / "r1.id")
    assert line == f"robot_1 {public_key_text(me.public_key)}"
    assert stat.S_IMODE(os.stat(tmp_path / "r1.id").st_mode) == 0o600
    other = Identity.generate("operator")
    other.save(tmp_path / "op.id")
    assert keys("add", str(roster), "operator", str(tmp_path / "op.id")) == 0
    assert keys("list", str(roster)) == 0
    listed = capsys.readouterr().out
    assert f"member  robot_1  {public_key_text(me.public_key)}" in listed
    assert f"member  operator  {public_key_text(other.public_key)}" in listed
    assert "permissions: none" in listed
    assert keys("revoke", str(roster), "operator") == 0
    loaded = Roster.load(roster)
    assert set(loaded.members) == {"robot_1"}
    assert loaded.revoked == [("operator", other.public_key)]
    capsys.readouterr()
    # a revoked key cannot come back, under any name
    assert keys("add", str(roster), "someone", public_key_text(other.public_key)) == 2
    assert "this key was revoked" in capsys.readouterr().err


def test_bad_input_is_a_one_line_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    roster = tmp_path / "fleet.roster"
    assert keys("revoke", str(roster), "nobody") == 2  # no such file
    assert "keys revoke" in capsys.readouterr().err
    assert keys("new", "a", "-o", str(tmp_path / "a.id"), "--roster", str(roster)) == 0
    assert keys("new", "a", "-o", str(tmp_path / "a.id")) == 2  # exists
    assert "use --force" in capsys.readouterr().err
    assert keys("add", str(roster), "b", "ed25519:nonsense") == 2
    assert "an Ed25519 key has 32 bytes" in capsys.readouterr().err
    assert keys("add", str(roster), "b", "ed25519:%%%") == 2
    assert "not valid base64" in capsys.readouterr().err
    assert keys("add", str(roster), "a", public_key_text(Identity.generate("x").public_key)) == 2
    assert "already a member" in capsys.readouterr().err
    assert keys("revoke", str(roster), "nobody") == 2
    assert "not a member" in capsys.readouterr().err
    (tmp_path / "broken.roster").write_text("members: [1, 2]\n")
    assert keys("list", str(tmp_path / "broken.roster")) == 2


def test_replace_gives_a_member_a_new_key_and_revokes_the_old(tmp_path: Path) -> None:
    roster = tmp_path / "fleet.roster"
    old, new = Identity.generate("a"), Identity.generate("a")
    assert keys("add", str(roster), "a", public_key_text(old.public_key)) == 0
    assert keys("add", str(roster), "a", public_key_text(new.public_key), "--replace") == 0
    loaded = Roster.load(roster)
    assert loaded.members == {"a": new.public_key}
    assert loaded.revoked == [("a", old.public_key)]


def test_the_policy_survives_keys_rewriting_the_roster(tmp_path: Path) -> None:
    roster = tmp_path / "fleet.roster"
    assert keys("new", "a", "-o", str(tmp_path / "a.id"), "--roster", str(roster)) == 0
    with roster.open("a") as out:
        out.write("permissions:\n  - {who: [a], may: [graph.start], targets: [robot_*]}\n")
    assert keys("new", "b", "-o", str(tmp_path / "b.id"), "--roster", str(roster)) == 0
    policy = Roster.load(roster).policy
    assert policy is not None
    assert policy.allows("a", "graph.start", "robot_7")
    assert not policy.allows("a", "graph.stop", "robot_7")
    assert not policy.allows("b", "graph.start", "robot_7")


@pytest.mark.parametrize(
    ("rules", "words"),
    [
        ({"who": ["a"]}, "may: a non-empty list"),
        ({"who": ["a"], "may": ["fly"]}, "matches no action"),
        ({"who": ["a"], "may": ["graph.*"], "on": ["x"]}, "who, may and targets"),
        ("not a rule", "who, may and targets"),
    ],
)
def test_a_bad_policy_is_refused_with_the_reason(rules: object, words: str) -> None:
    with pytest.raises(ValueError, match=words):
        Policy.from_data([rules])


def test_credentials_must_match_the_roster(tmp_path: Path) -> None:
    me = Identity.generate("a")
    me.save(tmp_path / "a.id")
    Roster({"a": Identity.generate("a").public_key}).save(tmp_path / "r")
    with pytest.raises(RosterError, match="another key for 'a'"):
        Credentials.load(tmp_path / "a.id", tmp_path / "r")
    Roster({}).save(tmp_path / "r")
    with pytest.raises(RosterError, match="not a member"):
        Credentials.load(tmp_path / "a.id", tmp_path / "r")


def test_the_cli_joins_with_an_identity_and_a_roster(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    assert keys("new", "a", "-o", str(tmp_path / "a.id"), "--roster", str(tmp_path / "r")) == 0
    args = argparse.Namespace(
        fleet_key_file=None,
        insecure=False,
        fleet_identity=str(tmp_path / "a.id"),
        fleet_roster=str(tmp_path / "r"),
    )
    got = fleet_key(args, "test")
    assert isinstance(got, Credentials)
    assert got.identity.name == "a"
    args.fleet_roster = None
    monkeypatch.delenv("TEMOTO_FLEET_ROSTER", raising=False)
    with pytest.raises(ConfigError, match="needs a roster"):
        fleet_key(args, "test")
    monkeypatch.setenv("TEMOTO_FLEET_ROSTER", str(tmp_path / "r"))
    assert isinstance(fleet_key(args, "test"), Credentials)


def test_serving_with_another_member_s_identity_is_a_one_line_error(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert keys("new", "a", "-o", str(tmp_path / "a.id"), "--roster", str(tmp_path / "r")) == 0
    capsys.readouterr()
    argv = ["serve", "--actor", "B", "--fleet-url", "inproc://keys-cli-serve"]
    argv += ["--fleet-identity", str(tmp_path / "a.id"), "--fleet-roster", str(tmp_path / "r")]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "the fleet identity names 'a', but this member is 'B'" in err
    assert "Traceback" not in err
