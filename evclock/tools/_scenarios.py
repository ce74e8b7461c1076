"""Finding scenarios: registered names, ``module:Name`` references and scenario files.

A scenario is a class following the interface of ``evclock_sims.Scenario`` (world set-up in
``__init__(client, seed)``, controllers in ``run(clock)``, ``success()``, ``summary()``,
``state_vector()``, and the class attributes ``name``, ``description``, ``default_until``).
Packages register theirs in the ``evclock.scenarios`` entry-point group (the bundled ones are
registered the same way), so ``evclock run NAME`` and ``evclock list`` find them.

Tunable parameters are the scenario class's public scalar class attributes (``bool``, ``int``,
``float``, ``str``); :func:`configure` returns a subclass with some of them overridden, which is
what ``--param name=value`` runs.

Engines: a scenario runs on PyBullet (the default) and, when its class attribute ``engines``
names ``"mujoco"``, on MuJoCo (``evclock run kuka --engine mujoco``). :func:`open_world` builds
the time source of the chosen engine and the scenario's world in it; only the scenario's
engine-facing code differs, its controllers are the same.
"""

from __future__ import annotations

import dataclasses
import hashlib
import importlib
import importlib.util
import math
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from evclock._errors import (
    EvClockError,
    InvalidArgumentError,
    InvalidTypeError,
    MissingExtraError,
    ScenarioError,
)
from evclock._extras import extra_for

if TYPE_CHECKING:
    from evclock.sources._stepping import SteppingTimeSource

ENGINES = ("pybullet", "mujoco")
"""The physics engines ``--engine`` chooses from; the first is the default."""

ENTRY_POINT_GROUP = "evclock.scenarios"
"""The entry-point group packages register their scenario classes in."""

_REQUIRED_METHODS = ("run", "success", "summary", "state_vector")
_REQUIRED_ATTRIBUTES = ("name", "description", "default_until")
# agent_controller: which controller an agent replaces (evclock.gym), not a tunable.
_NOT_PARAMETERS = frozenset((*_REQUIRED_ATTRIBUTES, "agent_controller"))
ParamValue = bool | int | float | str


@dataclasses.dataclass(frozen=True)
class RegisteredScenario:
    """One entry of the ``evclock.scenarios`` entry-point group."""

    name: str
    target: str
    """``module:Class`` the entry point names."""
    distribution: str
    """The installed distribution that registered it."""

    def load(self) -> type[Any]:
        """Import the scenario class (a broken registration raises :class:`ScenarioError`)."""
        return load_scenario(self.target, what=f"scenario {self.name!r} ({self.distribution})")


def registered_scenarios() -> list[RegisteredScenario]:
    """Every registered scenario, sorted by name then distribution (a stable order)."""
    import importlib.metadata  # only when scenarios are looked up: it is slow to import

    found = []
    for ep in importlib.metadata.entry_points(group=ENTRY_POINT_GROUP):
        dist = ep.dist.name if ep.dist is not None else "?"
        found.append(RegisteredScenario(ep.name, ep.value, dist))
    # Several environments can expose the same distribution twice on sys.path: keep one.
    unique = {(s.name, s.target, s.distribution): s for s in found}
    return sorted(unique.values(), key=lambda s: (s.name, s.distribution, s.target))


def _check_scenario_class(obj: object, what: str) -> type[Any]:
    if not isinstance(obj, type):
        raise InvalidTypeError(f"{what} is not a class but a {type(obj).__name__}")
    missing = [m for m in _REQUIRED_METHODS if not callable(getattr(obj, m, None))]
    missing += [a for a in _REQUIRED_ATTRIBUTES if not hasattr(obj, a)]
    if missing:
        raise InvalidTypeError(
            f"{what} ({obj.__module__}.{obj.__qualname__}) is not a scenario: it lacks "
            f"{', '.join(missing)}; subclass evclock_sims.Scenario (see the docs, "
            "guides/scenarios.md, 'Writing a scenario')"
        )
    abstract_methods = getattr(obj, "__abstractmethods__", None)
    if abstract_methods:
        abstract = ", ".join(sorted(abstract_methods))
        raise InvalidTypeError(f"{what} is abstract: implement {abstract}")
    return obj


def _module_from_file(path: Path) -> Any:
    if not path.is_file():
        raise InvalidArgumentError(f"scenario file {str(path)!r} does not exist")
    resolved = path.resolve()
    # One stable module name per file, so classes pickle and reload the same way everywhere.
    digest = hashlib.sha256(str(resolved).encode()).hexdigest()[:12]
    module_name = f"evclock_user_scenario_{resolved.stem}_{digest}"
    if module_name in sys.modules:
        return sys.modules[module_name]
    spec = importlib.util.spec_from_file_location(module_name, resolved)
    if spec is None or spec.loader is None:
        raise InvalidArgumentError(f"cannot import {str(path)!r} as a Python module")
    module = importlib.util.module_from_spec(spec)
    sys.modules[module_name] = module
    try:
        spec.loader.exec_module(module)
    except ModuleNotFoundError as exc:
        del sys.modules[module_name]
        raise _missing_module(exc, f"scenario file {str(path)!r}") from exc
    except BaseException:
        del sys.modules[module_name]
        raise
    return module


def _missing_module(exc: ModuleNotFoundError, what: str) -> EvClockError:
    """The error for a module ``what`` imports that is not installed: the extra that installs
    it (``pybullet``) or, for a module no extra provides, its name."""
    known = extra_for(exc, needed_by=what)
    if known is not None:
        return known
    return ScenarioError(
        f"{what} imports {exc.name!r}, which is not installed ({exc}); install it, or fix the "
        "import"
    )


def _scenario_classes_in(module: Any) -> list[type[Any]]:
    from evclock_sims import Scenario

    return [
        value
        for value in vars(module).values()
        if isinstance(value, type)
        and issubclass(value, Scenario)
        and value.__module__ == module.__name__
        and not getattr(value, "__abstractmethods__", None)
    ]


def split_file_reference(spec: str) -> tuple[str, str]:
    """``"dir/x.py:Name"`` -> ``("dir/x.py", "Name")``; ``"dir/x.py"`` -> ``("dir/x.py", "")``."""
    if ".py:" in spec:
        path, _, class_name = spec.rpartition(".py:")
        return path + ".py", class_name
    return spec, ""


def _load_from_file(text: str) -> type[Any]:
    path_text, class_name = split_file_reference(text)
    module = _module_from_file(Path(path_text))
    if class_name:
        if not hasattr(module, class_name):
            raise InvalidArgumentError(f"{path_text!r} defines no {class_name!r}")
        return _check_scenario_class(getattr(module, class_name), f"{text!r}")
    classes = _scenario_classes_in(module)
    if len(classes) != 1:
        names = ", ".join(cls.__name__ for cls in classes) or "none"
        raise InvalidArgumentError(
            f"{path_text!r} must define exactly one scenario class (a subclass of "
            f"evclock_sims.Scenario), found {names}; name one: {path_text}:ClassName"
        )
    return classes[0]


def is_file_reference(spec: str) -> bool:
    """Whether ``spec`` names a Python file (``path.py`` or ``path.py:Class``)."""
    return spec.endswith(".py") or ".py:" in spec or "/" in spec or "\\" in spec


def load_scenario(spec: str, *, what: str | None = None) -> type[Any]:
    """The scenario class ``spec`` names.

    ``spec`` is a registered name (``kuka``), a ``module:Class`` reference
    (``mypkg.scenarios:Reach``), a Python file (``path/to/scenario.py``, which must define
    exactly one scenario class) or ``path/to/scenario.py:Class``.

    :param spec: the scenario reference, as above.
    :param what: how error messages name the scenario (default: ``spec`` quoted).
    :returns: the scenario class (not an instance).
    :raises InvalidTypeError: ``spec`` is not a string, or names something that is not a
        concrete scenario class.
    :raises InvalidArgumentError: an unknown registered name, a missing file, or a file
        that does not define exactly one scenario class (or the named one).
    :raises ScenarioError: the module cannot be imported, lacks the attribute, or the
        name is registered more than once.

    Example::

        cls = load_scenario("mypkg.scenarios:Reach")
    """
    if not isinstance(spec, str):
        raise InvalidTypeError(f"a scenario is named by a string, got {type(spec).__name__}")
    label = what or f"{spec!r}"
    if is_file_reference(spec):
        return _load_from_file(spec)
    if ":" in spec:
        module_name, _, attribute = spec.partition(":")
        try:
            module = importlib.import_module(module_name)
        except ModuleNotFoundError as exc:
            missing = exc.name or ""
            if missing and module_name != missing and not module_name.startswith(missing + "."):
                # The module is there; something it imports is not.
                raise _missing_module(exc, label) from exc
            raise ScenarioError(
                f"cannot import {module_name!r} for {label}: {exc}; is the package installed "
                "(or on PYTHONPATH)?"
            ) from exc
        obj: Any = module
        for part in attribute.split("."):
            if not hasattr(obj, part):
                raise ScenarioError(f"{module_name!r} has no attribute {attribute!r} ({label})")
            obj = getattr(obj, part)
        return _check_scenario_class(obj, label)
    matches = [s for s in registered_scenarios() if s.name == spec]
    if not matches:
        valid = ", ".join(dict.fromkeys(s.name for s in registered_scenarios()))
        raise InvalidArgumentError(
            f"unknown scenario {spec!r}; registered names: {valid} "
            "(or give a file path.py or a module:Class)"
        )
    if len(matches) > 1:
        targets = "; ".join(f"{s.target} from {s.distribution}" for s in matches)
        raise ScenarioError(
            f"scenario name {spec!r} is registered more than once ({targets}); "
            "name the one you mean as module:Class"
        )
    return matches[0].load()


def parameters(cls: type[Any]) -> dict[str, ParamValue]:
    """The tunable parameters of scenario class ``cls`` and their defaults, sorted by name.

    They are the public class attributes (on ``cls`` or a base) holding a bool, int, float or
    str, except ``name``, ``description``, ``default_until`` and ``agent_controller``.

    :param cls: a scenario class (see :func:`load_scenario`).
    :returns: the default value of each parameter, by name.
    """
    found: dict[str, ParamValue] = {}
    for klass in reversed(cls.__mro__):
        for key, value in vars(klass).items():
            if key.startswith("_") or key in _NOT_PARAMETERS:
                continue
            if isinstance(value, bool | int | float | str):
                found[key] = value
            else:
                found.pop(key, None)
    return dict(sorted(found.items()))


def _parse_value(name: str, text: str, default: ParamValue) -> ParamValue:
    kind = type(default).__name__
    try:
        if isinstance(default, bool):
            lowered = text.strip().lower()
            if lowered not in ("true", "false", "1", "0"):
                raise InvalidArgumentError(text)  # reported below, with the parameter
            return lowered in ("true", "1")
        if isinstance(default, int):
            return int(text)
        if isinstance(default, float):
            value = float(text)
            if not math.isfinite(value):
                raise InvalidArgumentError(text)  # reported below, with the parameter
            return value
    except ValueError:
        raise InvalidArgumentError(
            f"parameter {name} takes a finite {kind} (its default is {default!r}), got {text!r}"
        ) from None
    return text


def parse_param_values(cls: type[Any], assignment: str) -> tuple[str, list[ParamValue]]:
    """``"name=v1,v2"`` -> ``(name, [v1, v2])``, each value converted to the default's type."""
    name, sep, values = assignment.partition("=")
    name = name.strip()
    if not sep or not name or not values.strip():
        raise InvalidArgumentError(
            f"--param takes name=value or name=v1,v2,..., got {assignment!r}"
        )
    tunable = parameters(cls)
    if name not in tunable:
        raise InvalidArgumentError(
            f"scenario {cls.name!r} has no parameter {name!r}; "
            f"its parameters: {', '.join(tunable) or 'none'}"
        )
    parsed = [_parse_value(name, part.strip(), tunable[name]) for part in values.split(",")]
    return name, parsed


def configure(cls: type[Any], params: dict[str, ParamValue]) -> type[Any]:
    """``cls`` with the class attributes ``params`` overridden (``cls`` itself when empty)."""
    if not params:
        return cls
    tunable = parameters(cls)
    for key, value in params.items():
        if key not in tunable:
            raise InvalidArgumentError(
                f"scenario {cls.name!r} has no parameter {key!r}; "
                f"its parameters: {', '.join(tunable) or 'none'}"
            )
        if type(value) is not type(tunable[key]):
            raise InvalidTypeError(
                f"parameter {key} of {cls.name!r} is a {type(tunable[key]).__name__}, got {value!r}"
            )
    return type(cls.__name__, (cls,), {"__module__": cls.__module__, **params})


def engines_of(cls: type[Any]) -> tuple[str, ...]:
    """The engines scenario class ``cls`` runs on: its ``engines`` attribute, else PyBullet.

    :param cls: a scenario class.
    :returns: engine names, from :data:`ENGINES`.
    """
    engines = getattr(cls, "engines", ("pybullet",))
    return tuple(engines)


def check_engine(cls: type[Any], engine: str) -> None:
    """Check that scenario class ``cls`` runs on ``engine``.

    :param cls: a scenario class.
    :param engine: ``"pybullet"`` or ``"mujoco"``.
    :raises InvalidTypeError: ``engine`` is not a string.
    :raises InvalidArgumentError: an unknown engine, or one the scenario does not run on.
    """
    if not isinstance(engine, str):
        raise InvalidTypeError(f"engine must be a string, got {type(engine).__name__}")
    if engine not in ENGINES:
        raise InvalidArgumentError(
            f"unknown engine {engine!r}; valid engines: {', '.join(ENGINES)}"
        )
    supported = engines_of(cls)
    if engine not in supported:
        raise InvalidArgumentError(
            f"scenario {cls.name!r} runs on {' and '.join(supported)} only, not on {engine}: "
            f"drop --engine {engine}"
        )


ENGINE_LABELS = {"pybullet": "PyBullet", "mujoco": "MuJoCo"}
"""How messages name each engine."""

_ENGINE_MODULES = {"pybullet": ("pybullet", "pybullet_data"), "mujoco": ("mujoco",)}

PYBULLET_WHEELS = (
    "PyBullet has wheels for CPython 3.11 only; on another Python pip builds it from source, "
    "which needs a C++ compiler and about half an hour"
)
"""Where ``pip install 'evclock[pybullet]'`` installs quickly, for messages that suggest it."""


def installed_engines() -> tuple[str, ...]:
    """The engines of :data:`ENGINES` whose modules are installed here (found, not imported).

    :returns: engine names, in the order of :data:`ENGINES`.
    """
    return tuple(
        engine
        for engine in ENGINES
        if all(importlib.util.find_spec(module) is not None for module in _ENGINE_MODULES[engine])
    )


def _install_hint(engine: str) -> str:
    hint = f"pip install 'evclock[{engine}]'"
    return f"{hint} ({PYBULLET_WHEELS})" if engine == "pybullet" else hint


def require_engine(cls: type[Any], engine: str) -> None:
    """Check that scenario class ``cls`` runs on ``engine`` (:func:`check_engine`) and that
    ``engine`` is installed: the one check every command and option takes before a run.

    :param cls: a scenario class.
    :param engine: ``"pybullet"`` or ``"mujoco"``.
    :raises InvalidTypeError: ``engine`` is not a string.
    :raises InvalidArgumentError: an unknown engine, or one the scenario does not run on (the
        message names the engines it runs on, and how to install them when none is).
    :raises MissingExtraError: ``engine`` is not installed; the message names the extra, where
        it installs, and the scenario's other engine when it has one.
    """
    installed = installed_engines()
    supported = engines_of(cls)
    if (
        isinstance(engine, str)
        and engine in ENGINES
        and engine not in supported
        and not any(e in installed for e in supported)
    ):
        labels = " and ".join(ENGINE_LABELS.get(e, e) for e in supported)
        raise InvalidArgumentError(
            f"scenario {cls.name!r} runs on {labels} only, not on {ENGINE_LABELS[engine]}, "
            f"and {labels} is not installed here: " + "; ".join(_install_hint(e) for e in supported)
        )
    check_engine(cls, engine)
    if engine in installed:
        return
    label = ENGINE_LABELS[engine]
    others = [e for e in supported if e != engine]
    if engine == "pybullet" and others:
        other = others[0]
        how = f"--engine {other}"
        if other not in installed:
            how = f"{_install_hint(other)}, then {how}"
        message = (
            f"scenario {cls.name!r} runs on {label} by default, which is not installed: "
            f"{_install_hint(engine)}; or run it on {ENGINE_LABELS[other]}: {how}"
        )
    elif others:
        message = f"--engine {engine}: {label} is not installed: {_install_hint(engine)}"
        if others[0] in installed:
            message += (
                f"; or drop --engine {engine} to run {cls.name!r} on {ENGINE_LABELS[others[0]]}"
            )
    else:
        message = (
            f"scenario {cls.name!r} runs on {label} only, which is not installed: "
            f"{_install_hint(engine)}"
        )
    error = MissingExtraError(message, name=_ENGINE_MODULES[engine][0])
    error.extra = engine
    raise error


def open_engine(
    cls: type[Any], engine: str = "pybullet", *, gui: bool = False
) -> tuple[SteppingTimeSource[Any] | None, Any]:
    """The world scenario class ``cls`` is built in on ``engine``, and its time source when it
    exists before the world is built.

    On PyBullet: a :class:`~evclock.sources.PyBulletTimeSource` with a new DIRECT (or GUI)
    client, and that client's id as the world. On MuJoCo: no source yet (MuJoCo compiles a
    whole model at once) and an empty ``evclock_sims.MuJoCoWorld``; build the scenario in it
    (``cls(world, seed)``), then take ``world.time_source()``. :func:`open_world` does both.

    :param cls: a scenario class (see :func:`load_scenario`).
    :param engine: ``"pybullet"`` (default) or ``"mujoco"``.
    :param gui: open PyBullet's GUI (PyBullet only).
    :returns: ``(source or None, world)``.
    :raises InvalidArgumentError: an unknown or unsupported engine, or ``gui`` on MuJoCo.
    :raises MissingExtraError: the engine is not installed; the message names its extra.
    """
    require_engine(cls, engine)
    if engine == "mujoco":
        if gui:
            raise InvalidArgumentError(
                "--gui opens PyBullet's GUI, which MuJoCo runs do not have: drop --gui"
            )
        from evclock_sims import MuJoCoWorld

        return None, MuJoCoWorld()
    from evclock.sources import PyBulletTimeSource

    source = PyBulletTimeSource.connect(gui=gui)
    return source, source.client


def open_world(
    cls: type[Any], seed: int, *, engine: str = "pybullet", gui: bool = False
) -> tuple[SteppingTimeSource[Any], Any]:
    """The time source of ``engine`` and scenario ``cls`` set up in it with ``seed``.

    See :func:`open_engine`. The caller closes the source.

    :param cls: a scenario class (see :func:`load_scenario`).
    :param seed: the seed the scenario is set up with.
    :param engine: ``"pybullet"`` (default) or ``"mujoco"``.
    :param gui: open PyBullet's GUI (PyBullet only).
    :returns: ``(source, scenario)``.
    :raises InvalidArgumentError: an unknown or unsupported engine, or ``gui`` on MuJoCo.
    :raises MissingExtraError: the engine is not installed; the message names its extra.

    Example::

        source, scenario = open_world(load_scenario("kuka"), 0, engine="mujoco")
    """
    source, world = open_engine(cls, engine, gui=gui)
    try:
        scenario = cls(world, seed)
        if source is None:
            source = world.time_source()
    except BaseException:
        if source is not None:
            source.close()
        raise
    assert source is not None
    return source, scenario
