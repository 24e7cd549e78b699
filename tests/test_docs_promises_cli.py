"""Sentences of the README and docs/deployment.md, docs/ros2.md that no other test held
(docs/promises.md maps each sentence to its test): every command has `--help`, the commands that
talk to the stack share one set of options, the key layout, the cores import without zenoh, what
each deployment profile starts, the local profile stays on loopback and ROS 2 turns gossip on.
All in process (the cores' import in one child process), no stack started.
"""

from __future__ import annotations

import contextlib
import dataclasses
import inspect
import io
import json
import re
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

import smana.deploy
from smana.common import keys
from smana.common.cli import doc_summary
from smana.common.config import SmanaConfig
from smana.deploy.cli import COMMANDS, _usage, main
from smana.deploy.router import router_config
from smana.deploy.supervisor import Supervisor
from smana.lab.bench import BENCHES

PROFILES = Path(smana.deploy.__file__).parent / "profiles"

# The README: "The commands that run or talk to the stack (...) take the same options".
STACK_COMMANDS = (
    "up",
    "status",
    "sim",
    "mapper",
    "navgraph",
    "planner",
    "explorer",
    "coordinator",
    "replay",
    "ros2",
    "plan",
    "goto",
    "view",
    "router",
)
SHARED_OPTIONS = (
    "--config",
    "--set",
    "--robot",
    "--run-dir",
    "--mode",
    "--connect",
    "--listen",
    "--zenoh-config",
    "--no-multicast-scouting",
)


def help_of(*argv: str) -> tuple[int, str]:
    """`smana <argv> --help` in this process: (exit status, what it printed)."""
    out = io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(out):
        try:
            code = main([*argv, "--help"])
        except SystemExit as exc:
            code = exc.code
    return code, out.getvalue()


def test_smana_help_lists_every_command_and_each_has_help():
    listed = _usage()
    for name in COMMANDS:
        assert f"\n  {name} " in listed, name
    for argv in [(name,) for name in COMMANDS] + [("bench", b) for b in BENCHES]:
        code, text = help_of(*argv)
        assert code == 0, (argv, text)
        assert text.startswith("usage: smana "), (argv, text[:200])


def test_every_commands_help_describes_it_in_whole_sentences():
    """`smana <command> --help` (and `smana experiment <name> --help`) describes the command in
    whole sentences: a description cut at its docstring's first line ("... into the") fails."""
    argv = [(name,) for name in COMMANDS] + [("experiment", "resources")]
    cut = []
    for args in argv:
        code, text = help_of(*args)
        assert code == 0, (args, text)
        paragraphs = [" ".join(p.split()) for p in text.split("\n\n")]
        description = paragraphs[1] if len(paragraphs) > 1 else ""
        if description.startswith(("positional arguments:", "options:")):
            description = ""  # none given
        if description and not description.endswith((".", ")", ".)")):
            cut.append((args, description))
    assert not cut, cut


@pytest.mark.parametrize("command", STACK_COMMANDS)
def test_the_commands_that_talk_to_the_stack_take_the_shared_options(command):
    code, text = help_of(command)
    assert code == 0, text
    options = set(text.replace(",", " ").split())
    missing = [o for o in SHARED_OPTIONS if o not in options]
    assert not missing, (command, missing)


def test_a_key_is_smana_robot_service_topic_with_r1_by_default():
    robot = SmanaConfig.load().general.robot
    assert robot == "r1"
    assert keys.status(robot, "mapper") == "smana/r1/mapper/status"
    assert keys.query(robot, "planner", "path") == "smana/r1/planner/path"
    assert keys.map_delta("r7") == "smana/r7/mapper/delta"


def test_the_cores_import_without_zenoh():
    """Every module of the mapper, navgraph, planner and sim packages but the zenoh wiring
    (`service`, `__main__`, the service's frame `finishing` worker) and the command-line tools."""
    code = (
        "import importlib, pkgutil, sys\n"
        "wiring = {'service', '__main__', 'finishing', 'plan_cli', 'world_cli'}\n"
        "n = 0\n"
        "for pkg in ('mapper', 'navgraph', 'planner', 'sim'):\n"
        "    p = importlib.import_module('smana.services.' + pkg)\n"
        "    for m in pkgutil.walk_packages(p.__path__, p.__name__ + '.'):\n"
        "        if m.name.rsplit('.', 1)[1] not in wiring:\n"
        "            importlib.import_module(m.name)\n"
        "            n += 1\n"
        "print(n, 'zenoh' in sys.modules)\n"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    n, zenoh_loaded = r.stdout.split()
    assert int(n) >= 20 and zenoh_loaded == "False", r.stdout


def supervisor_of(profile: str, tmp_path: Path, *overrides: str) -> Supervisor:
    cfg = SmanaConfig.load(None, list(overrides), layers=[PROFILES / f"{profile}.toml"])
    return Supervisor(cfg, tmp_path / profile)


@pytest.mark.parametrize(
    "profile,services",
    [
        ("local", {"sim", "mapper", "navgraph", "planner", "explorer"}),
        ("robot", {"sim", "mapper"}),
        ("base", {"navgraph", "planner", "explorer"}),
        (
            "multi-robot",
            {f"{s}@{r}" for s in ("navgraph", "planner", "explorer") for r in "r1 r2".split()},
        ),
        ("fleet", {"mapper@fleet", "navgraph@fleet", "coordinator@fleet"}),
        ("fleet-robot", {"mapper@r1", "planner@r1", "explorer@r1"}),
    ],
)
def test_each_profile_runs_the_services_of_its_row(tmp_path, profile, services):
    """docs/deployment.md's profile table, the services column (the recorder is added by `smana
    up` itself) and the router column: loopback for the services, TLS towards the other host."""
    sup = supervisor_of(profile, tmp_path)
    assert set(sup.procs) == services
    d = sup.config.deploy
    assert d.router_listen[0] == "tcp/127.0.0.1:7447"
    if profile in ("robot", "fleet-robot"):
        assert [e.split("/")[0] for e in d.router_connect] == ["tls"]
    elif profile != "local":
        assert "tls/0.0.0.0:7448" in d.router_listen and not d.router_connect


def router_args(monkeypatch, sup: Supervisor) -> tuple:
    """The arguments `Supervisor.start` opens its router with (nothing is opened)."""
    seen = []

    class Opened(Exception):
        pass

    def fake_open_router(listen, zc, connect=()):
        seen.append((list(listen), zc, list(connect)))
        raise Opened

    monkeypatch.setattr("smana.deploy.router.open_router", fake_open_router)
    with pytest.raises(Opened):
        sup.start()
    return seen[0]


def test_the_local_profile_keeps_everything_on_loopback(tmp_path, monkeypatch):
    sup = supervisor_of("local", tmp_path)
    listen, zc, connect = router_args(monkeypatch, sup)
    conf = router_config(listen, zc, connect)
    assert json.loads(conf.get_json("listen/endpoints")) == ["tcp/127.0.0.1:7447"]
    assert json.loads(conf.get_json("connect/endpoints")) in ([], {"router": []})
    assert json.loads(conf.get_json("scouting/multicast/enabled")) is False
    assert json.loads(conf.get_json("scouting/gossip/enabled")) is False
    # every service is a client of that router and of nothing else
    svc = sup.service_config.zenoh
    assert (svc.mode, svc.connect, svc.listen) == ("client", ["tcp/127.0.0.1:7447"], [])
    assert not svc.multicast_scouting and not svc.gossip


def test_ros2_enabled_turns_gossip_on_in_the_router(tmp_path, monkeypatch):
    _, zc, _ = router_args(monkeypatch, supervisor_of("local", tmp_path))
    assert zc.gossip is False
    on = supervisor_of("local", tmp_path / "on", "deploy.ros2.enabled=true")
    _, zc, _ = router_args(monkeypatch, on)
    assert zc.gossip is True
    assert json.loads(router_config(["tcp/127.0.0.1:7447"], zc).get_json("scouting/gossip/enabled"))
    # under access control (the secured profile's router) gossip stays off: peers that learnt
    # each other's locators could link directly and bypass the policy
    policy = tmp_path / "acl.json5"
    policy.write_text("{}")
    acl = supervisor_of(
        "local", tmp_path / "acl", "deploy.ros2.enabled=true", f'zenoh.acl_file="{policy}"'
    )
    _, zc, _ = router_args(monkeypatch, acl)
    assert zc.gossip is False


def test_set_reaches_nested_tables_and_config_toml_holds_every_key(tmp_path):
    """The README's `--set explorer.follower.lookahead_m=0.3`; the tutorial's "every key of every
    section, with its value, is in the run directory's config.toml"."""
    from smana.common.config.section import items

    cfg = SmanaConfig.load(None, ["explorer.follower.lookahead_m=0.3"])
    assert cfg.explorer.follower.lookahead_m == 0.3
    sup = Supervisor(cfg, tmp_path / "run", services=[])
    text = sup.config_path.read_text()
    written = tomllib.loads(text)

    def paths(obj, prefix=""):
        for name, value in items(obj):  # the fields, and the back-ends' and worlds' sections
            if dataclasses.is_dataclass(value):
                yield from paths(value, f"{prefix}{name}.")
            else:
                yield prefix + name

    missing = []
    for path in paths(cfg):
        node = written
        for part in path.split("."):
            node = node.get(part, KeyError) if isinstance(node, dict) else KeyError
        if node is KeyError:
            missing.append(path)
    assert not missing, missing
    assert written["explorer"]["follower"]["lookahead_m"] == 0.3


def test_smana_up_prints_one_line_of_every_service_every_ten_seconds(tmp_path, capsys):
    assert inspect.signature(Supervisor.run).parameters["progress_period_s"].default == 10.0
    sup = supervisor_of("local", tmp_path)
    sup.print_progress(10.0)
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == 1, lines
    for name in ("sim", "mapper", "navgraph", "planner", "explorer"):
        assert f"{name}:down" in lines[0], lines[0]  # its state: nothing was started


def test_a_profile_is_a_layer_under_config_and_set_and_the_help_names_each(tmp_path):
    """docs/deployment.md: `--profile NAME` (a TOML layer under deploy/profiles/, or any TOML
    file) with `--config` and `--set` on top of it; `smana up --help` names every bundled one."""
    from smana.deploy.supervisor import profile_path

    bundled = sorted(p.stem for p in PROFILES.glob("*.toml"))
    assert {"local", "robot", "base", "multi-robot", "fleet", "fleet-robot"} <= set(bundled)
    _, text = help_of("up")
    profile_help = " ".join(text.split("--profile PROFILE")[-1].split("--only")[0].split())
    for name in bundled:
        assert re.search(rf"(?<![\w-]){re.escape(name)}(?![\w-])", profile_help), name
    mine = tmp_path / "my.toml"
    mine.write_text('[deploy]\nrouter_connect = ["tcp/10.0.0.2:7447"]\n')
    assert profile_path(str(mine)) == mine
    robot = profile_path("robot")
    assert SmanaConfig.load(None, [], layers=[robot]).deploy.router_connect[0].startswith("tls/")
    on_top = tmp_path / "on_top.toml"
    on_top.write_text(
        '[deploy]\nrouter_connect = ["tls/10.0.0.9:7448"]\n[mapper]\nresolution_m = 0.2\n'
    )
    cfg = SmanaConfig.load(on_top, ["mapper.resolution_m=0.3"], layers=[robot])
    assert cfg.deploy.router_connect == ["tls/10.0.0.9:7448"]  # --config over the profile
    assert cfg.mapper.resolution_m == 0.3  # --set over --config
    assert not cfg.deploy.navgraph.enabled  # what neither changed stays the profile's


def test_a_duration_in_a_help_text_says_it_was_measured_once():
    """A time in `--help` is a measurement on one machine, not a promise: each help text that
    gives one says so ("measured once"); the figures are in docs/benchmarks.md."""
    helps = [(name,) for name in COMMANDS] + [("bench", b) for b in BENCHES]
    helps += [
        ("experiment", e)
        for e in (
            "noise",
            "exploration",
            "ablation",
            "routes",
            "fleet",
            "resources",
            "navnoise",
            "risk",
            "robustness",
        )
    ]
    timed = 0
    for argv in helps:
        _, text = help_of(*argv)
        flat = " ".join(text.split())
        for said in re.finditer(r"about (a|[\d.]+) (s|min|minutes?)\b", flat):
            window = flat[max(0, said.start() - 400) : said.start()]
            assert "measured once" in window, (argv, flat[said.start() - 120 : said.end()])
            timed += 1
    assert timed >= 15


def test_world_info_gives_bounds_objects_and_free_space(capsys):
    """The README: `smana world info  # the default world: bounds, objects, free space, as JSON`."""
    from smana.services.sim.world_cli import cli

    assert cli(["info"]) in (0, None)
    info = json.loads(capsys.readouterr().out)
    assert len(info["bounds"]) == 4 and sum(info["objects"].values()) > 0, info
    assert 0 < info["free_fraction"] < 1, info
    # "First steps, in the default world (a 12 m garden, seed 3; ...)"
    assert info["name"] == "garden-3" and info["bounds"] == [-6.0, -6.0, 6.0, 6.0], info


@pytest.mark.parametrize("name", sorted(BENCHES))
def test_a_benchs_help_says_what_it_does_in_whole_sentences(name, capsys):
    """`smana bench <name> --help` describes the bench by its module's first paragraph, not a
    first line that may stop mid-sentence ("... through mapper, navgraph and")."""
    import importlib

    module, func = BENCHES[name].split(":")
    with pytest.raises(SystemExit) as e:
        getattr(importlib.import_module(module), func)(["--help"])
    assert e.value.code == 0
    out = capsys.readouterr().out
    description = " ".join(out.split("\n\n")[1].split())
    assert description.startswith(f"`smana bench {name}"), description
    whole = doc_summary(importlib.import_module(module).__doc__)
    assert description.replace(" ", "") == whole.replace(" ", ""), description  # argparse wraps
    assert description.endswith((".", ")")), description
