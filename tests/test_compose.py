"""compose.yaml and the Dockerfile, read the way Docker reads them (no Docker needed).

Also the home of the small compose reader (variable interpolation, service definitions) that
``tests/integration`` uses to start every service from its compose definition.
"""

from __future__ import annotations

import importlib.util
import os
import re
import shlex
import shutil
import subprocess
import sys
import tomllib
import zipfile
from collections.abc import Mapping
from pathlib import Path, PurePosixPath
from typing import Any

import pytest
import yaml

REPO = Path(__file__).resolve().parent.parent
COMPOSE_FILE = REPO / "compose.yaml"
DOCKERFILE = REPO / "Dockerfile"
DOCKERIGNORE = REPO / ".dockerignore"
VENV_BIN = Path(sys.executable).parent

INFRASTRUCTURE = ("redis", "postgres")
ONE_SHOT = ("migrate",)
LONG_RUNNING = ("api", "scheduler", "render-worker", "train-worker", "detect-worker")
# Services compose starts only when their profile is asked for (`--profile NAME`).
PROFILED = {"flower": ["monitoring"], "train-worker-gpu": ["gpu"]}
# What each service runs, hence which extras of pyproject the image must carry.
EXTRAS_NEEDED = {
    "migrate": set(),
    "api": {"api"},
    "flower": {"api"},
    # The scheduler samples θ, which reads the default assets (scikit-image's pictures).
    "scheduler": {"render"},
    "render-worker": {"render"},
    "train-worker": {"train"},
    "train-worker-gpu": {"train"},
    "detect-worker": {"train"},
}


# --------------------------------------------------------------------------- the reader


class ComposeError(ValueError):
    """compose.yaml says something compose would refuse (or that this reader does not know)."""


# ${NAME}, ${NAME:-default}, ${NAME-default}, ${NAME:?error}, ${NAME?error}, ${NAME:+alt},
# ${NAME+alt}, $NAME, and $$ for a literal dollar: compose's interpolation syntax.
_VARIABLE = re.compile(
    r"\$(?:(?P<escaped>\$)"
    r"|\{(?P<braced>[A-Za-z_][A-Za-z0-9_]*)(?:(?P<op>:?[-?+])(?P<arg>[^}]*))?\}"
    r"|(?P<bare>[A-Za-z_][A-Za-z0-9_]*)"
    r"|(?P<invalid>))"
)


def interpolate(text: str, variables: Mapping[str, str]) -> str:
    """Substitute ``${...}`` the way ``docker compose`` does, from ``variables`` (its environment + .env)."""

    def substitute(match: re.Match) -> str:
        if match["escaped"]:
            return "$"
        if match["invalid"] is not None:
            raise ComposeError(f"invalid interpolation in {text!r} at offset {match.start()}")
        name = match["braced"] or match["bare"]
        value = variables.get(name)
        op, arg = match["op"], match["arg"]
        if op is None:
            return value or ""
        unset_or_empty = not value
        missing = unset_or_empty if op.startswith(":") else value is None
        if op.endswith("-"):
            return arg if missing else value
        if op.endswith("?"):
            if missing:
                raise ComposeError(f"required variable {name} is missing a value: {arg}")
            return value
        return "" if missing else arg  # ":+" / "+": the alternative when set

    return _VARIABLE.sub(substitute, text)


def _interpolate_tree(node: Any, variables: Mapping[str, str]) -> Any:
    if isinstance(node, str):
        return interpolate(node, variables)
    if isinstance(node, list):
        return [_interpolate_tree(item, variables) for item in node]
    if isinstance(node, dict):
        return {key: _interpolate_tree(value, variables) for key, value in node.items()}
    return node


def load_compose_text(text: str, variables: Mapping[str, str] | None = None) -> dict[str, Any]:
    """Parse a compose file (anchors and ``<<`` merges included) and interpolate its values."""
    document = yaml.safe_load(text)
    if not isinstance(document, dict) or not isinstance(document.get("services"), dict):
        raise ComposeError("a compose file needs a top-level 'services' mapping")
    return _interpolate_tree(document, variables or {})


def load_compose(variables: Mapping[str, str] | None = None) -> dict[str, Any]:
    return load_compose_text(COMPOSE_FILE.read_text(), variables)


def service_command(service: Mapping[str, Any]) -> list[str]:
    command = service.get("command")
    if command is None:
        raise ComposeError("service has no command (the image's CMD is only `foldwise --help`)")
    return shlex.split(command) if isinstance(command, str) else [str(part) for part in command]


def service_environment(service: Mapping[str, Any]) -> dict[str, str]:
    """``environment`` as a dict, from either of compose's two spellings (mapping or KEY=VALUE list)."""
    environment = service.get("environment") or {}
    if isinstance(environment, list):
        pairs = (entry.split("=", 1) for entry in environment)
        return {pair[0]: pair[1] if len(pair) == 2 else "" for pair in pairs}
    return {key: "" if value is None else str(value) for key, value in environment.items()}


def foldwise_services(compose: Mapping[str, Any]) -> dict[str, dict[str, Any]]:
    """The services that run the foldwise image (they build it)."""
    return {name: service for name, service in compose["services"].items() if "build" in service}


def volume_mounts(service: Mapping[str, Any]) -> dict[str, str]:
    """target path -> source, for short (``src:dst[:mode]``) and long volume syntax."""
    mounts = {}
    for volume in service.get("volumes", []):
        if isinstance(volume, str):
            source, target = volume.split(":")[:2]
        else:
            source, target = volume.get("source", ""), volume["target"]
        mounts[target] = source
    return mounts


def run_help(argv: list[str]) -> subprocess.Popen:
    """Start ``argv --help`` with the venv's executables (argv[0] is a console script name)."""
    executable = VENV_BIN / argv[0]
    return subprocess.Popen(
        [str(executable), *argv[1:], "--help"],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        cwd=REPO,
    )


# --------------------------------------------------------------------------- the Dockerfile reader


def dockerfile_instructions(text: str) -> list[tuple[str, str]]:
    """(INSTRUCTION, arguments) with line continuations joined and comments dropped."""
    instructions: list[tuple[str, str]] = []
    pending = ""
    for raw in text.splitlines():
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        if line.endswith("\\"):
            pending += line[:-1] + " "
            continue
        line, pending = pending + line, ""
        keyword, _, arguments = line.partition(" ")
        instructions.append((keyword.upper(), arguments.strip()))
    if pending:
        raise ValueError("Dockerfile ends inside a line continuation")
    return instructions


def expand_extras(extras: set[str], optional: Mapping[str, list[str]], project: str = "foldwise") -> set[str]:
    """Extras plus the ones they pull in through self-references like ``foldwise[render,train]``."""
    expanded, todo = set(), list(extras)
    while todo:
        extra = todo.pop()
        if extra in expanded:
            continue
        if extra not in optional:
            raise KeyError(f"pyproject.toml has no extra {extra!r}")
        expanded.add(extra)
        for requirement in optional[extra]:
            match = re.fullmatch(rf"{project}\[([^\]]+)\]", requirement.replace(" ", ""))
            if match:
                todo.extend(match[1].split(","))
    return expanded


# --------------------------------------------------------------------------- the reader itself


@pytest.mark.parametrize(
    ("text", "variables", "expected"),
    [
        ("${A:-x}", {}, "x"),
        ("${A:-x}", {"A": ""}, "x"),
        ("${A-x}", {"A": ""}, ""),
        ("${A-x}", {}, "x"),
        ("${A:-x}", {"A": "set"}, "set"),
        ("${A:+alt}", {"A": "set"}, "alt"),
        ("${A:+alt}", {}, ""),
        ("$A/${B}", {"A": "a", "B": "b"}, "a/b"),
        ("${MISSING}", {}, ""),
        ("cost: $$5 and $${A}", {"A": "no"}, "cost: $5 and ${A}"),
        ("${A:-http://h:1/0}", {}, "http://h:1/0"),
    ],
)
def test_interpolation_follows_compose_rules(text, variables, expected):
    assert interpolate(text, variables) == expected


@pytest.mark.parametrize(
    ("text", "message"),
    [("${TOKEN:?set it in .env}", "TOKEN is missing a value: set it in .env"), ("a $ b", "invalid interpolation")],
)
def test_interpolation_refuses_what_compose_refuses(text, message):
    with pytest.raises(ComposeError, match=re.escape(message)):
        interpolate(text, {"TOKEN": ""})


def test_reader_refuses_a_file_without_services():
    with pytest.raises(ComposeError, match="top-level 'services'"):
        load_compose_text("version: '3'\n")


# --------------------------------------------------------------------------- compose.yaml


@pytest.fixture(scope="module")
def compose() -> dict[str, Any]:
    return load_compose({"FOLDWISE_API_TOKEN": "t0ken"})


def test_compose_refuses_to_start_without_a_token():
    for variables in ({}, {"FOLDWISE_API_TOKEN": ""}):
        with pytest.raises(
            ComposeError, match="required variable FOLDWISE_API_TOKEN is missing a value: set FOLDWISE_API_TOKEN"
        ):
            load_compose(variables)


def test_every_role_of_the_design_is_a_service(compose):
    assert set(compose["services"]) == {*INFRASTRUCTURE, *ONE_SHOT, *LONG_RUNNING, *PROFILED}
    assert set(foldwise_services(compose)) == {*ONE_SHOT, *LONG_RUNNING, *PROFILED}


@pytest.mark.parametrize("name", INFRASTRUCTURE)
def test_redis_and_postgres_report_their_health(compose, name):
    healthcheck = compose["services"][name]["healthcheck"]
    assert healthcheck["test"][0] in ("CMD", "CMD-SHELL") and len(healthcheck["test"]) > 1
    assert healthcheck.get("retries", 3) >= 3
    assert compose["services"][name]["restart"] in ("always", "unless-stopped")


@pytest.mark.parametrize("name", [*LONG_RUNNING, "train-worker-gpu"])
def test_long_running_services_wait_for_healthy_infrastructure_and_the_migration(compose, name):
    service = compose["services"][name]
    assert service["depends_on"] == {
        "redis": {"condition": "service_healthy"},
        "postgres": {"condition": "service_healthy"},
        "migrate": {"condition": "service_completed_successfully"},
    }
    assert service["restart"] in ("always", "unless-stopped", "on-failure")


def test_migrate_is_one_shot_and_needs_only_the_database(compose):
    migrate = compose["services"]["migrate"]
    assert service_command(migrate) == ["foldwise", "db", "upgrade"]
    assert migrate["depends_on"] == {"postgres": {"condition": "service_healthy"}}
    # Restarting a finished migration would keep compose from seeing it complete.
    assert migrate["restart"] == "no"
    assert "ports" not in migrate


def test_render_workers_can_be_scaled(compose):
    for name in ("render-worker", "train-worker", "scheduler"):
        service = compose["services"][name]
        assert "container_name" not in service, f"{name}: a fixed container name forbids --scale"
        assert "ports" not in service, f"{name}: a fixed host port forbids --scale"


def test_no_service_names_its_container(compose):
    assert all("container_name" not in service for service in compose["services"].values())


def test_foldwise_services_share_one_definition_and_one_artifact_store(compose):
    services = foldwise_services(compose)
    images = {service["image"] for service in services.values()}
    assert len(images) == 1
    # An anchor, not copies: PyYAML hands every alias of one anchor the very same object.
    raw = yaml.safe_load(COMPOSE_FILE.read_text())["services"]
    environments = [raw[name]["environment"] for name in services]
    assert all(environment is environments[0] for environment in environments)
    for name, service in services.items():
        data_dir = service_environment(service)["FOLDWISE_DATA_DIR"]
        assert volume_mounts(service).get(data_dir) == "artifacts", f"{name} does not mount the store at {data_dir}"
        # The texture check's cache outlives a container: a restarted detect worker reads it back.
        cache_dir = PurePosixPath(service_environment(service)["FOLDWISE_CACHE_DIR"])
        assert cache_dir.is_relative_to(data_dir) and cache_dir != PurePosixPath(data_dir), (
            f"{name} keeps its cache outside the store"
        )
    assert "artifacts" in compose["volumes"]


def test_foldwise_services_reach_infrastructure_by_service_name(compose):
    environment = service_environment(compose["services"]["scheduler"])
    assert environment["FOLDWISE_DATABASE_URL"].startswith("postgresql+psycopg://foldwise:foldwise@postgres:5432/")
    assert environment["FOLDWISE_BROKER_URL"] == "redis://redis:6379/0"
    postgres = service_environment(compose["services"]["postgres"])
    assert environment["FOLDWISE_DATABASE_URL"].endswith(f"/{postgres['POSTGRES_DB']}")


def test_token_port_and_password_come_from_the_environment_or_dotenv():
    compose = load_compose(
        {
            "FOLDWISE_API_TOKEN": "t0ken",
            "FOLDWISE_API_PORT": "9001",
            "POSTGRES_PASSWORD": "pw",
            "FOLDWISE_API_BIND": "0.0.0.0",
        }
    )
    api = compose["services"]["api"]
    environment = service_environment(api)
    assert environment["FOLDWISE_API_TOKEN"] == "t0ken"
    assert environment["FOLDWISE_DATABASE_URL"].startswith("postgresql+psycopg://foldwise:pw@postgres")
    assert service_environment(compose["services"]["postgres"])["POSTGRES_PASSWORD"] == "pw"
    assert api["ports"] == ["0.0.0.0:9001:8000"]


def test_api_is_published_on_8000_by_default_and_listens_where_it_is_published(compose):
    api = compose["services"]["api"]
    assert api["ports"] == ["127.0.0.1:8000:8000"]
    command = service_command(api)
    container_port = api["ports"][0].rsplit(":", 1)[1]
    assert command[command.index("--port") + 1] == container_port
    assert command[command.index("--host") + 1] == "0.0.0.0"
    assert "/health" in " ".join(api["healthcheck"]["test"])


def test_flower_and_the_gpu_worker_are_only_in_their_profiles(compose):
    profiles = {name: s["profiles"] for name, s in compose["services"].items() if "profiles" in s}
    assert profiles == PROFILED


def test_the_gpu_train_worker_reserves_one_nvidia_device_and_runs_the_train_worker(compose):
    gpu, cpu = compose["services"]["train-worker-gpu"], compose["services"]["train-worker"]
    (device,) = gpu["deploy"]["resources"]["reservations"]["devices"]
    assert device == {"driver": "nvidia", "count": 1, "capabilities": ["gpu"]}
    # the same role, image and store as the CPU train worker; only the device differs
    assert service_command(gpu) == service_command(cpu)
    assert gpu["image"] == cpu["image"] and volume_mounts(gpu) == volume_mounts(cpu)
    assert "deploy" not in cpu, "the default stack must start on a machine without a GPU"


def test_every_service_command_is_a_real_cli_command(compose):
    commands = {name: service_command(s) for name, s in foldwise_services(compose).items()}
    assert {argv[0] for argv in commands.values()} <= {"foldwise", "celery"}
    # A wrong sub-command or option must fail this same check (else the check proves nothing).
    control = {
        "(control) unknown command": ["foldwise", "no-such-role"],
        "(control) unknown option": ["foldwise", "api", "--hots", "x"],
    }
    processes = {name: run_help(argv) for name, argv in {**commands, **control}.items()}
    results = {name: (process.wait(timeout=60), process.stdout.read()) for name, process in processes.items()}
    for name, (code, output) in results.items():
        if name.startswith("(control)"):
            assert code != 0, f"{name} passed `--help`: the check cannot tell a bad command"
        else:
            assert code == 0, f"{name}: `{' '.join(commands[name])} --help` exited {code}:\n{output[-2000:]}"
            assert "Usage" in output


# --------------------------------------------------------------------------- the Dockerfile


@pytest.fixture(scope="module")
def instructions() -> list[tuple[str, str]]:
    return dockerfile_instructions(DOCKERFILE.read_text())


@pytest.fixture(scope="module")
def pyproject() -> dict[str, Any]:
    return tomllib.loads((REPO / "pyproject.toml").read_text())


def test_image_is_python_of_the_project_and_runs_unprivileged(instructions, pyproject):
    bases = [arguments.split()[0] for keyword, arguments in instructions if keyword == "FROM"]
    assert bases and all(base == "python:3.11-slim-bookworm" for base in bases)
    assert pyproject["project"]["requires-python"] == "==3.11.*"
    users = [arguments for keyword, arguments in instructions if keyword == "USER"]
    assert users and users[-1] not in ("root", "0")
    assert ("CMD", '["foldwise", "--help"]') in instructions


def test_image_installs_pinned_versions_with_every_extra_the_services_need(instructions, pyproject):
    runs = [arguments for keyword, arguments in instructions if keyword == "RUN"]
    installs = [run for run in runs if "pip install" in run and "-c constraints.txt" in run]
    extras_installed: set[str] = set()
    for run in installs:
        for extras in re.findall(r"\.\[([a-z,]+)\]", run):
            extras_installed |= set(extras.split(","))
    assert extras_installed, "no `pip install -c constraints.txt '.[...]'` in the Dockerfile"
    optional = pyproject["project"]["optional-dependencies"]
    provided = expand_extras(extras_installed, optional)
    for service, needed in EXTRAS_NEEDED.items():
        assert needed <= provided, f"{service} needs extras {needed - provided} the image lacks"
    assert "dev" not in provided, "test tools do not belong in the image"
    # The Makefile installs the same way, so the image runs what the tests ran.
    assert "-c constraints.txt" in (REPO / "Makefile").read_text()
    # Every pin the project makes exactly is what constraints.txt pins.
    pins = dict(line.split("==", 1) for line in (REPO / "constraints.txt").read_text().splitlines() if "==" in line)
    for requirement in [r for extra in optional.values() for r in extra] + pyproject["project"]["dependencies"]:
        if "==" in requirement:
            name, version = requirement.split("==")
            assert pins.get(name) == version, f"constraints.txt pins {name} to {pins.get(name)}, pyproject to {version}"


def test_dependencies_are_installed_before_the_code_is_copied(instructions):
    """A code change must not invalidate the layer that installs torch and bpy."""
    final_stage = instructions[max(i for i, (k, _) in enumerate(instructions) if k == "FROM") :]
    heavy = next(i for i, (k, a) in enumerate(final_stage) if k == "RUN" and ".[all]" in a)
    code_dirs = ("foldwise", "db", "workers", "services")
    for keyword, arguments in final_stage[:heavy]:
        if keyword == "COPY":
            sources = arguments.split()[:-1]
            assert not any(s.rstrip("/") in code_dirs for s in sources), f"COPY {arguments} before the dependencies"


def test_image_data_dir_is_the_compose_volume(instructions, compose):
    environment = " ".join(arguments for keyword, arguments in instructions if keyword == "ENV")
    assert "FOLDWISE_DATA_DIR=/data" in environment
    assert "FOLDWISE_CONFIGS_DIR=/app/configs" in environment
    for service in foldwise_services(compose).values():
        assert "/data" in volume_mounts(service)


def test_everything_copied_exists_and_is_in_the_build_context(instructions):
    allowed = {line[1:].rstrip("/") for line in DOCKERIGNORE.read_text().splitlines() if line.startswith("!")}
    assert "*" in DOCKERIGNORE.read_text().splitlines(), ".dockerignore should allow-list, starting from '*'"
    for keyword, arguments in instructions:
        if keyword != "COPY" or "--from" in arguments:
            continue
        for source in [s for s in arguments.split() if not s.startswith("--")][:-1]:
            name = source.rstrip("/").rstrip("*")
            assert name in allowed, f"COPY {source}: .dockerignore keeps it out of the build context"
            if not source.endswith("*"):  # a trailing * marks an optional file
                assert (REPO / name).exists(), f"COPY {source}: no such path in the repository"
    for excluded in (".venv", ".git", "var", "tests"):
        assert excluded not in allowed


def test_the_wheel_the_image_installs_carries_the_code_and_migrates_from_outside_the_repository(tmp_path):
    """The image installs a wheel (not the editable checkout the tests use): build it as the
    Dockerfile's wheel stage does, from only what that stage copies, and run it from elsewhere."""
    instructions = dockerfile_instructions(DOCKERFILE.read_text())
    stage_start = next(i for i, (k, a) in enumerate(instructions) if k == "FROM" and a.endswith(" AS wheel"))
    stage_end = next(i for i, (k, _) in enumerate(instructions) if k == "FROM" and i > stage_start)
    source = tmp_path / "src"
    source.mkdir()
    for keyword, arguments in instructions[stage_start:stage_end]:
        if keyword != "COPY":
            continue
        for item in arguments.split()[:-1]:
            path = REPO / item.rstrip("*").rstrip("/")
            if path.is_dir():
                shutil.copytree(path, source / path.name, ignore=shutil.ignore_patterns("__pycache__"))
            elif path.exists():
                shutil.copy2(path, source / path.name)
    built = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--quiet", "--no-deps", "--no-build-isolation", "--wheel-dir",
         str(tmp_path / "wheels"), str(source)],
        capture_output=True, text=True, timeout=120, check=False,
    )  # fmt: skip
    assert built.returncode == 0, built.stderr[-2000:]
    (wheel,) = (tmp_path / "wheels").glob("foldwise-*.whl")

    packaged = set(zipfile.ZipFile(wheel).namelist())
    modules = {
        path.relative_to(REPO).as_posix()
        for package in ("foldwise", "db", "workers", "services")
        for path in (REPO / package).rglob("*.py")
        if "__pycache__" not in path.parts
    }
    assert modules - packaged == set(), "modules the image would lack"
    assert any(name.startswith("db/migrations/versions/") for name in packaged)

    # Unpacked ahead of the editable checkout on sys.path, run from a directory that is not
    # the repository, with the configs where the image puts them.
    site = tmp_path / "site"
    zipfile.ZipFile(wheel).extractall(site)
    configs = shutil.copytree(REPO / "configs", tmp_path / "app" / "configs")
    database = tmp_path / "data" / "foldwise.db"
    environment = {
        **{k: v for k, v in os.environ.items() if not k.startswith("FOLDWISE_")},
        "PYTHONPATH": str(site),
        "FOLDWISE_DATA_DIR": str(tmp_path / "data"),
        "FOLDWISE_CONFIGS_DIR": str(configs),
    }
    script = (
        "import sys, foldwise, db\n"
        f"assert foldwise.__file__.startswith({str(site)!r}), foldwise.__file__\n"
        "from foldwise.conditions import load_condition_table\n"
        "print(sorted(load_condition_table().table3))\n"
        "from services.cli import main\n"
        "sys.argv = ['foldwise', 'db', 'upgrade']\n"
        "main()\n"
    )
    ran = subprocess.run(
        [sys.executable, "-c", script], cwd=tmp_path / "app", env=environment,
        capture_output=True, text=True, timeout=120, check=False,
    )  # fmt: skip
    assert ran.returncode == 0, ran.stdout[-2000:] + ran.stderr[-2000:]
    assert "['de', 'eo', 'fb', 'li', 'mb', 'po', 'sc']" in ran.stdout
    assert "database at head" in ran.stdout and database.is_file()


# A kernel of the render package that compiles in seconds: the one the compile step below must
# compile itself, where the others are seeded from what `make install` compiled.
HELD_BACK_KERNEL = "assets._two_colour_pattern-"


def seed_numba_cache(cache_dir: Path) -> Path | None:
    """Seed ``cache_dir``, as a NUMBA_CACHE_DIR, with the render kernels `make install` compiled
    into workers/render/__pycache__, all but HELD_BACK_KERNEL: a step run on it loads those
    instead of compiling them again (about a minute and a half of CPU). Returns the folder numba
    reads and writes workers/render's kernels in under ``cache_dir`` (numba's
    ``_UserProvidedCacheLocator``: the folder's name and the SHA-1 of its absolute path), or None
    where no compiled kernel is there to seed from."""
    import hashlib

    source = REPO / "workers" / "render"
    compiled = [
        path
        for pattern in ("*.nbi", "*.nbc")
        for path in (source / "__pycache__").glob(pattern)
        if not path.name.startswith(HELD_BACK_KERNEL)
    ]
    if not compiled:
        return None
    folder = cache_dir / f"render_{hashlib.sha1(os.path.abspath(source).encode()).hexdigest()}"
    folder.mkdir(parents=True)
    for path in compiled:
        shutil.copy2(path, folder / path.name)
    return folder


def test_image_compiles_the_render_kernels_into_a_cache_its_workers_load(instructions, tmp_path):
    """The Dockerfile's compile step, run as written with its NUMBA_CACHE_DIR (moved under
    tmp_path), leaves a cache from which a later process runs every kernel the pipeline needs
    without compiling one. The cache starts with what `make install` compiled, less one kernel:
    the step compiles that one and writes it there (any other it finds out of date, too)."""
    environment_lines = " ".join(arguments for keyword, arguments in instructions if keyword == "ENV")
    (cache_dir,) = re.findall(r"NUMBA_CACHE_DIR=(\S+)", environment_lines)
    runs = [arguments for keyword, arguments in instructions if keyword == "RUN" and "compile_kernels" in arguments]
    assert len(runs) == 1 and f"chown -R foldwise:foldwise {cache_dir}" in runs[0]
    compile_at = next(i for i, (k, a) in enumerate(instructions) if k == "RUN" and "compile_kernels" in a)
    users = [i for i, (k, _) in enumerate(instructions) if k == "USER"]
    assert users[-1] > compile_at, "the runtime user is set after the kernels are compiled"
    command = re.search(r'python -c "([^"]+)"', runs[0]).group(1)
    environment = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / cache_dir.lstrip("/"))}
    seeded = seed_numba_cache(tmp_path / cache_dir.lstrip("/"))
    compiled = subprocess.run(
        [sys.executable, "-c", command], env=environment, cwd=REPO, capture_output=True, text=True, timeout=300
    )
    assert compiled.returncode == 0, compiled.stderr[-2000:]
    assert list((tmp_path / cache_dir.lstrip("/")).rglob("*.nbi")), "the compile step wrote no numba cache"
    if seeded is not None:
        assert list(seeded.glob(f"{HELD_BACK_KERNEL}*.nbi")), "the compile step wrote no cache where it was seeded"
    # A later process: the same step again, then count compilations against cache loads over
    # every numba kernel of the render package.
    check = (
        f"{command}\n"
        "import numba.core.registry, sys\n"
        "kernels = [v for name, m in list(sys.modules.items()) if name.startswith('workers.render')\n"
        "           for v in vars(m).values() if isinstance(v, numba.core.registry.CPUDispatcher)]\n"
        "print(sum(sum(k.stats.cache_misses.values()) for k in kernels), sum(sum(k.stats.cache_hits.values()) for k in kernels))\n"
    )
    loaded = subprocess.run(
        [sys.executable, "-c", check], env=environment, cwd=REPO, capture_output=True, text=True, timeout=300
    )
    assert loaded.returncode == 0, loaded.stderr[-2000:]
    misses, hits = map(int, loaded.stdout.split())
    assert misses == 0 and hits >= 10, (misses, hits)


def test_make_install_compiles_the_render_kernels_as_the_image_does(instructions):
    """`make install` (the first `make run` or `make test`) ends with the Dockerfile's own compile
    step, after the packages are in and before the stamp that marks the install done, so no
    curriculum of `make run` compiles the kernels inside the run's time (the step itself is run
    and checked above)."""
    makefile = (REPO / "Makefile").read_text()
    recipe = makefile.split("$(STAMP): pyproject.toml constraints.txt\n", 1)[1].split("\n\n", 1)[0].splitlines()
    (image_step,) = [
        arguments for keyword, arguments in instructions if keyword == "RUN" and "compile_kernels" in arguments
    ]
    command = re.search(r'python -c "([^"]+)"', image_step).group(1)
    compiles = [i for i, line in enumerate(recipe) if command in line]
    installs = [i for i, line in enumerate(recipe) if "pip install" in line and "-e '.[dev]'" in line]
    stamps = [i for i, line in enumerate(recipe) if line.strip() == "touch $(STAMP)"]
    assert len(compiles) == len(installs) == len(stamps) == 1, recipe
    assert installs[0] < compiles[0] < stamps[0], recipe


# The shared libraries bpy's extension module needs from the system (its NEEDED entries, through
# the libraries bundled in the wheel), and the Debian package that provides each in the image.
# A library missing here is one a new bpy wants: find its package (`dpkg -S`) and add both.
BASE_IMAGE = "in python:3.11-slim-bookworm"
SYSTEM_LIBRARY_PACKAGES = {
    "ld-linux-x86-64.so.2": BASE_IMAGE,
    "libc.so.6": BASE_IMAGE,
    "libdl.so.2": BASE_IMAGE,
    "libm.so.6": BASE_IMAGE,
    "libpthread.so.0": BASE_IMAGE,
    "librt.so.1": BASE_IMAGE,
    "libutil.so.1": BASE_IMAGE,
    "libgcc_s.so.1": BASE_IMAGE,
    "libstdc++.so.6": BASE_IMAGE,
    "libGL.so.1": "libgl1",
    "libICE.so.6": "libice6",
    "libSM.so.6": "libsm6",
    "libX11.so.6": "libx11-6",
    "libXext.so.6": "libxext6",
    "libXfixes.so.3": "libxfixes3",
    "libXi.so.6": "libxi6",
    "libXrender.so.1": "libxrender1",
    "libxkbcommon.so.0": "libxkbcommon0",
}


def needed_system_libraries(extension: Path) -> set[str]:
    """Sonames ``extension`` needs, directly or through libraries in its own ``lib/`` folder."""
    bundled = {path.name: path for path in (extension.parent / "lib").glob("*.so*")}
    seen: set[Path] = set()
    system: set[str] = set()
    todo = [extension]
    while todo:
        path = todo.pop()
        if path in seen:
            continue
        seen.add(path)
        dynamic = subprocess.run(["readelf", "-d", str(path)], capture_output=True, text=True, check=True).stdout
        for soname in re.findall(r"\(NEEDED\)\s+Shared library: \[(.+?)\]", dynamic):
            if soname in bundled:
                todo.append(bundled[soname])
            else:
                system.add(soname)
    return system


def test_image_has_the_system_libraries_bpy_links_against(instructions):
    spec = importlib.util.find_spec("bpy")
    if spec is None or not spec.origin:
        pytest.skip("bpy is not installed here")
    if shutil.which("readelf") is None:
        pytest.skip("readelf (binutils) is not installed here")
    needed = needed_system_libraries(Path(spec.origin))
    assert needed, f"no NEEDED entries read from {spec.origin}"
    unknown = needed - set(SYSTEM_LIBRARY_PACKAGES)
    assert not unknown, f"bpy needs {sorted(unknown)}: add their Debian packages to the Dockerfile and this table"
    apt_installs = [a for k, a in instructions if k == "RUN" and "apt-get install" in a]
    assert len(apt_installs) == 1
    installed = set(apt_installs[0].split("apt-get install", 1)[1].split("&&")[0].split())
    for soname in sorted(needed):
        package = SYSTEM_LIBRARY_PACKAGES[soname]
        assert package == BASE_IMAGE or package in installed, f"{soname}: the image does not install {package}"
