"""Shared command-line behaviour: negative coordinates are values (`--to -1.9,5.3`), and every
command that builds a world takes it from the config the way `smana up` does."""

from __future__ import annotations

import json

import pytest

from smana.common.cli import ArgumentParser, point, positive_float
from smana.common.config import SmanaConfig
from smana.services.planner.plan_cli import parser as plan_parser
from smana.services.sim.world_cli import cli as world_cli
from tests.test_cli_misuse import NO_SCOUT, free_port, one_line_misuse, smana


def _parser() -> ArgumentParser:
    p = ArgumentParser(prog="smana test")
    p.add_argument("--to", type=point)
    p.add_argument("--offset", type=float)
    p.add_argument("--duration", type=positive_float)
    p.add_argument("--flag", action="store_true")
    return p


@pytest.mark.parametrize(
    "text, value",
    [
        ("-1.9,5.3", (-1.9, 5.3)),
        ("-2,-3", (-2.0, -3.0)),
        ("-.5,1e1,-4", (-0.5, 10.0, -4.0)),
        ("-1.5E-1,+2", (-0.15, 2.0)),
        ("0,-1", (0.0, -1.0)),
    ],
)
def test_a_negative_number_list_is_a_value(text, value):
    assert _parser().parse_args(["--to", text]).to == pytest.approx(value)


def test_negative_scalars_still_parse_and_options_are_still_options():
    args = _parser().parse_args(["--offset", "-2.5e2", "--flag", "--to", "-1,-1"])
    assert args.offset == -250.0 and args.flag and args.to == (-1.0, -1.0)


@pytest.mark.parametrize(
    "argv, words",
    [
        (["--to", "-x"], ["--to", "expected one argument"]),  # not a number: an option
        (["--to", "-1"], ["--to", "expected X,Y in metres", "'-1'"]),  # a value, refused
        (["--to", "-1,2,3,4"], ["expected X,Y in metres"]),
        (["--to", "1,nan"], ["expected X,Y in metres"]),
        (["--duration", "-5"], ["--duration", "expected a number > 0, got '-5'"]),
        (["-7,1"], ["unrecognized arguments: -7,1"]),  # a stray value is not a mystery option
    ],
)
def test_refusals_are_one_line(capsys, argv, words):
    with pytest.raises(SystemExit) as exc:
        _parser().parse_args(argv)
    err = capsys.readouterr().err
    assert exc.value.code == 2 and len(err.strip().splitlines()) == 1, err
    for w in words:
        assert w in err, (w, err)


def test_plan_takes_negative_coordinates():
    args = plan_parser().parse_args(["--from", "-0.5,-0", "--to", "-1.9,5.3"])
    assert args.start == (-0.5, 0.0) and args.goal == (-1.9, 5.3)


def test_smana_plan_with_a_negative_goal_gets_past_its_arguments():
    # no stack: a refused argument would say so; an accepted one goes on to connect
    r = smana(
        "plan",
        "--from",
        "0,0",
        "--to",
        "-1.9,5.3",
        "--connect",
        f"tcp/127.0.0.1:{free_port()}",
        NO_SCOUT,
    )
    one_line_misuse(r, "plan", "cannot connect to")


def test_smana_world_subcommands_take_negative_values_too(capsys):
    # subparsers inherit the parser class: `-3` reaches --seed's own check, which refuses it
    with pytest.raises(SystemExit):
        world_cli(["info", "--seed", "-3"])
    err = capsys.readouterr().err
    assert "argument --seed: expected an integer >= 0, got '-3'" in err, err


# -- one default world -----------------------------------------------------------------------


def _world_args(argv):
    from smana.services.sim import world_cli as wc

    p = ArgumentParser(prog="smana world")
    wc._world_args(p)
    return wc.sim_config_from_args(p.parse_args(argv))


def test_smana_world_defaults_to_the_world_smana_up_explores():
    sim, classes = _world_args([])
    up = SmanaConfig.load()  # what `smana up` loads with no --config and no --set
    assert sim == up.sim and sim.seed == 3 and sim.world == "garden"
    assert classes == up.general.class_table


def test_smana_world_reads_config_and_set_then_its_own_flags(tmp_path):
    path = tmp_path / "c.toml"
    path.write_text("[sim]\nseed = 7\n[sim.garden]\nsize_m = 8.0\n")
    sim, _ = _world_args(["--config", str(path)])
    assert (sim.seed, sim.garden.size_m) == (7, 8.0)
    sim, _ = _world_args(["--config", str(path), "--set", "sim.seed=9"])
    assert (sim.seed, sim.garden.size_m) == (9, 8.0)
    sim, _ = _world_args(["--config", str(path), "--seed", "4", "--size", "6"])
    assert (sim.seed, sim.garden.size_m) == (4, 6.0)
    assert SmanaConfig.load(path).sim.garden == _world_args(["--config", str(path)])[0].garden


def test_world_info_is_the_same_world_by_flag_or_by_config(tmp_path, capsys):
    def info(*argv) -> dict:
        assert world_cli(["info", "--set", "sim.garden.size_m=5", *argv]) == 0
        return json.loads(capsys.readouterr().out)

    by_flag = info("--seed", "2")
    assert info("--set", "sim.seed=2") == by_flag
    assert info() != by_flag  # the default (3) is another garden


def test_a_bad_world_config_is_one_line():
    r = smana("world", "info", "--set", "sim.seed=x")
    one_line_misuse(r, "world", "sim.seed")
