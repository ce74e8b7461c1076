"""Finding scenarios: registered names, files, module:Class, third-party entry points, params."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from _cli import run_evclock
from typer.testing import CliRunner

import evclock
from evclock.tools._cli import app
from evclock.tools._scenarios import configure, load_scenario, parameters, parse_param_values

ROOT = Path(__file__).resolve().parents[2]
SHUTTLE = ROOT / "examples" / "shuttle_scenario.py"
runner = CliRunner()


@pytest.mark.pybullet
def test_registered_names_load_the_bundled_classes() -> None:
    from evclock_sims import CartPole, HuskyPatrol, KukaReach

    assert load_scenario("kuka") is KukaReach
    assert load_scenario("husky") is HuskyPatrol
    assert load_scenario("cartpole") is CartPole
    names = [s.name for s in evclock.tools._scenarios.registered_scenarios()]
    assert {"kuka", "husky", "cartpole"} <= set(names)


@pytest.mark.pybullet
def test_module_reference_and_file_load_the_same_kind_of_class() -> None:
    from evclock_sims import CartPole

    assert load_scenario("evclock_sims.cartpole:CartPole") is CartPole
    shuttle = load_scenario(str(SHUTTLE))
    assert shuttle.name == "shuttle"
    assert load_scenario(f"{SHUTTLE}:Shuttle") is shuttle  # one module per file, loaded once


@pytest.mark.pybullet
@pytest.mark.parametrize(
    ("spec", "error", "message"),
    [
        ("nope", evclock.InvalidArgumentError, "unknown scenario 'nope'; registered names: "),
        ("no/such/file.py", evclock.InvalidArgumentError, "scenario file 'no/such/file.py' does"),
        ("no_such_module_x:Thing", evclock.tools.ScenarioError, "cannot import 'no_such_module_x'"),
        ("evclock_sims.cartpole:Nope", evclock.tools.ScenarioError, "has no attribute 'Nope'"),
        ("evclock_sims.cartpole:SLIDER", evclock.InvalidTypeError, "is not a class but a int"),
        ("evclock:Time", evclock.InvalidTypeError, "is not a scenario: it lacks run, success"),
        (
            "evclock_sims:Scenario",
            evclock.InvalidTypeError,
            "it lacks name, description, default_until",
        ),
    ],
)
def test_bad_references_fail_with_clear_messages(
    spec: str, error: type[Exception], message: str
) -> None:
    with pytest.raises(error, match=None) as info:
        load_scenario(spec)
    assert message in str(info.value)


@pytest.mark.pybullet
def test_a_file_must_define_exactly_one_scenario(tmp_path: Path) -> None:
    two = tmp_path / "two.py"
    two.write_text(
        "from evclock_sims.cartpole import CartPole\n"
        "class A(CartPole):\n    name = 'a'\n"
        "class B(CartPole):\n    name = 'b'\n"
    )
    with pytest.raises(evclock.InvalidArgumentError) as info:
        load_scenario(str(two))
    assert "must define exactly one scenario class" in str(info.value)
    assert "found A, B; name one: " in str(info.value)
    assert load_scenario(f"{two}:B").name == "b"


@pytest.mark.pybullet
def test_parameters_are_public_scalar_class_attributes() -> None:
    shuttle = load_scenario(str(SHUTTLE))
    assert parameters(shuttle) == {
        "control_hz": 20.0,
        "gain": 3.0,
        "hold_time": 0.5,
        "max_speed": 1.5,
        "tolerance": 0.01,
    }
    assert parse_param_values(shuttle, "gain=1,2.5") == ("gain", [1.0, 2.5])
    tuned = configure(shuttle, {"gain": 5.0})
    assert tuned.gain == 5.0
    assert shuttle.gain == 3.0
    assert tuned.name == "shuttle"
    assert issubclass(tuned, shuttle)


@pytest.mark.pybullet
@pytest.mark.parametrize(
    ("assignment", "message"),
    [
        ("gain", "--param takes name=value or name=v1,v2,..., got 'gain'"),
        ("speed=1", "scenario 'shuttle' has no parameter 'speed'; its parameters: control_hz,"),
        ("gain=fast", "parameter gain takes a finite float (its default is 3.0), got 'fast'"),
        ("gain=nan", "parameter gain takes a finite float"),
    ],
)
def test_bad_params_fail_clearly(assignment: str, message: str) -> None:
    with pytest.raises(evclock.InvalidArgumentError) as info:
        parse_param_values(load_scenario(str(SHUTTLE)), assignment)
    assert message in str(info.value)


@pytest.mark.pybullet
def test_configure_rejects_a_value_of_the_wrong_type() -> None:
    with pytest.raises(evclock.InvalidTypeError) as info:
        configure(load_scenario(str(SHUTTLE)), {"gain": "3"})
    assert "parameter gain of 'shuttle' is a float, got '3'" in str(info.value)


@pytest.mark.pybullet
def test_run_a_scenario_file_with_a_param_changes_the_run() -> None:
    base = evclock.tools.run_scenario(str(SHUTTLE), seed=2)
    slow = evclock.tools.run_scenario(str(SHUTTLE), seed=2, params={"gain": 1.0})
    assert base.success
    assert slow.success
    assert slow.params == {"gain": 1.0}
    assert slow.summary["target_m"] == base.summary["target_m"]  # same seed, same target
    assert slow.sim_time_s > base.sim_time_s  # a lower gain arrives later


@pytest.mark.pybullet
def test_cli_runs_a_file_and_a_module_reference() -> None:
    result = runner.invoke(app, ["run", str(SHUTTLE), "--seed", "1", "--quiet"])
    assert result.exit_code == 0, result.output
    assert "shuttle (seed 1): SUCCESS" in result.output
    result = runner.invoke(app, ["run", "evclock_sims.cartpole:CartPole", "--until", "31"])
    assert result.exit_code == 0, result.output
    assert "cartpole (seed 0): SUCCESS" in result.output


@pytest.mark.pybullet
def test_cli_rejects_several_values_in_run() -> None:
    result = runner.invoke(app, ["run", str(SHUTTLE), "--param", "gain=1,2"])
    assert result.exit_code == 2
    assert "evclock run takes one value per --param (gain); use evclock sweep" in " ".join(
        result.output.split()
    )


def _third_party(tmp_path: Path, names: dict[str, str]) -> dict[str, str]:
    """A real installed-style distribution on PYTHONPATH registering ``names``."""
    package = tmp_path / "acme_robots"
    package.mkdir()
    (package / "__init__.py").write_text("")
    (package / "shuttles.py").write_text(SHUTTLE.read_text().replace('"shuttle"', '"acme"'))
    dist = tmp_path / "acme_robots-1.0.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: acme-robots\nVersion: 1.0\n")
    entries = "".join(f"{name} = {target}\n" for name, target in names.items())
    (dist / "entry_points.txt").write_text(f"[evclock.scenarios]\n{entries}")
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(tmp_path), env.get("PYTHONPATH", "")])
    return env


@pytest.mark.pybullet
def test_third_party_packages_register_scenarios_by_entry_point(tmp_path: Path) -> None:
    env = _third_party(tmp_path, {"acme": "acme_robots.shuttles:Shuttle"})
    listed = run_evclock("list", env=env)
    assert listed.returncode == 0, listed.stderr
    assert "acme" in listed.stdout
    assert "acme-robots" in listed.stdout
    assert "kuka" in listed.stdout
    ran = run_evclock("run", "acme", "--seed", "4", "--quiet", env=env)
    assert ran.returncode == 0, ran.stdout + ran.stderr
    assert "acme (seed 4): SUCCESS" in ran.stdout


def test_a_name_registered_twice_must_be_named_precisely(tmp_path: Path) -> None:
    env = _third_party(tmp_path, {"kuka": "acme_robots.shuttles:Shuttle"})
    ran = run_evclock("run", "kuka", "--quiet", env=env)
    assert ran.returncode == 2
    message = " ".join(ran.stderr.split())
    assert "scenario name 'kuka' is registered more than once" in message
    assert "acme_robots.shuttles:Shuttle from acme-robots" in message
    assert "name the one you mean as module:Class" in message
