"""The service's import rules, read from the source with ``ast`` (module-level and function-level imports alike):

- the API (``app/`` outside ``app/core``) never imports the workers (``worker``);
- the workers import ``app.core`` and nothing else of ``app``;
- ``app/core`` imports neither the workers nor the API modules;
- the engine (``voxnerf/``) imports neither the service (``app``, ``worker``) nor a web library, but for the
  command line (``voxnerf.cli``: ``serve`` and ``worker`` start them) and the service's client (``voxnerf.client``),
  which imports of the service only the models its requests and answers are checked with;
- no two files of ``voxnerf/``, ``app/`` or ``worker/`` import each other in a cycle (a function-level import or
  one for type checking counts: each is a dependency all the same);

and, by running it, that the API process does not load torch: building the ASGI app and serving requests
that need no scene validation imports neither ``torch`` nor the engine's model nor open3d. Importing the
workers' tasks builds no Celery app and no model cache.
"""

from __future__ import annotations

import ast
import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
HEAVY_MODULES = ("torch", "voxnerf.model.voxnerf_model", "open3d")


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _imports(path: Path) -> set[str]:
    """Every module ``path`` imports anywhere in its body (see :func:`_imports_in`)."""
    return _imports_in(path.read_text(), _module_name(path), path.name == "__init__.py")


def _imports_in(source: str, module: str, is_package: bool = False) -> set[str]:
    """The modules ``source`` (module ``module``) imports, at any depth; ``from a import b`` counts as ``a.b``
    (b may be a module), relative imports are resolved against the module's package."""
    package = module if is_package else module.rpartition(".")[0]
    found: set[str] = set()
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = package.split(".")
                anchor = parts[: len(parts) - (node.level - 1)]
                base = ".".join(anchor + ([base] if base else []))
            found.update(f"{base}.{alias.name}" for alias in node.names)
    return found


def _modules(folder: str) -> list[Path]:
    return sorted((ROOT / folder).rglob("*.py"))


def _under(name: str, package: str) -> bool:
    return name == package or name.startswith(package + ".")


CORE = [p for p in _modules("app") if _under(_module_name(p), "app.core")]
API = [p for p in _modules("app") if not _under(_module_name(p), "app.core")]
WORKER = _modules("worker")


def test_the_three_groups_are_not_empty():
    assert CORE and API and WORKER
    assert ROOT / "app" / "main.py" in API and ROOT / "app" / "core" / "jobstore.py" in CORE


@pytest.mark.parametrize("path", API, ids=lambda p: str(p.relative_to(ROOT)))
def test_api_modules_do_not_import_the_workers(path: Path):
    bad = sorted(name for name in _imports(path) if _under(name, "worker"))
    assert not bad, f"{path.relative_to(ROOT)} imports {bad}: share the code through app.core instead"


@pytest.mark.parametrize("path", WORKER, ids=lambda p: str(p.relative_to(ROOT)))
def test_worker_modules_import_only_the_core_of_app(path: Path):
    bad = sorted(
        name for name in _imports(path) if _under(name, "app") and not _under(name, "app.core")
    )
    assert not bad, f"{path.relative_to(ROOT)} imports {bad}: only app.core is shared with the workers"


@pytest.mark.parametrize("path", CORE, ids=lambda p: str(p.relative_to(ROOT)))
def test_core_modules_import_neither_the_api_nor_the_workers(path: Path):
    bad = sorted(
        name
        for name in _imports(path)
        if _under(name, "worker") or (_under(name, "app") and not _under(name, "app.core"))
    )
    assert not bad, f"{path.relative_to(ROOT)} imports {bad}: app.core must not depend on its users"


ENGINE = [p for p in _modules("voxnerf")
          if not (_under(_module_name(p), "voxnerf.cli") or _under(_module_name(p), "voxnerf.client"))]
CLIENT = [p for p in _modules("voxnerf") if _under(_module_name(p), "voxnerf.client")]
WEB_PACKAGES = ("app", "worker", "fastapi", "starlette", "uvicorn", "httpx", "celery", "kombu", "sqlalchemy")
CLIENT_MAY_IMPORT = ("app.schemas", "app.core.render_request")  # the models the API checks requests and answers with


def test_engine_and_client_groups_are_not_empty():
    assert ROOT / "voxnerf" / "config.py" in ENGINE and ROOT / "voxnerf" / "client" / "api.py" in CLIENT


@pytest.mark.parametrize("path", ENGINE, ids=lambda p: str(p.relative_to(ROOT)))
def test_the_engine_imports_no_service_and_no_web_library(path: Path):
    bad = sorted(name for name in _imports(path) if any(_under(name, package) for package in WEB_PACKAGES))
    assert not bad, f"{path.relative_to(ROOT)} imports {bad}: the engine stays free of the service"


@pytest.mark.parametrize("path", CLIENT, ids=lambda p: str(p.relative_to(ROOT)))
def test_the_client_imports_of_the_service_only_its_request_and_answer_models(path: Path):
    bad = sorted(name for name in _imports(path)
                 if (_under(name, "app") and not any(_under(name, model) for model in CLIENT_MAY_IMPORT))
                 or _under(name, "worker"))
    assert not bad, f"{path.relative_to(ROOT)} imports {bad}: the client shares only the API's models"


def _module_graph() -> dict[str, set[str]]:
    """Module -> the project modules it imports (``from a import b`` is module ``a.b`` when that file exists, else
    ``a``), over every file of voxnerf/, app/ and worker/."""
    paths = {_module_name(p): p for folder in ("voxnerf", "app", "worker") for p in _modules(folder)}
    graph = {}
    for module, path in paths.items():
        targets = {name if name in paths else name.rpartition(".")[0] for name in _imports(path)}
        graph[module] = {t for t in targets if t in paths and t != module}
    return graph


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of ``graph`` with more than one module (Tarjan's algorithm, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found = []
    for root in sorted(graph):
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph[child]))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                if len(component) > 1:
                    found.append(sorted(component))
    return found


def test_no_import_cycle_between_the_project_s_files():
    graph = _module_graph()
    assert "worker.tasks" in graph and "voxnerf.synthetic.geometry" in graph
    cycles = _cycles(graph)
    assert not cycles, f"import cycles (each a set of modules that import each other): {cycles}"


def test_the_cycle_finder_finds_a_cycle_and_only_cycles():
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}, "e": set(), "f": {"g"}, "g": {"f"}}
    assert sorted(_cycles(graph)) == [["a", "b", "c"], ["f", "g"]]
    assert _cycles({"a": {"b"}, "b": set()}) == []


def test_the_import_reader_sees_function_level_and_relative_imports():
    source = "def f():\n    from worker.tasks import x\n    from . import jobstore\n    import app.main\n"
    found = _imports_in(source, "app.core.example")
    assert {"worker.tasks.x", "app.core.jobstore", "app.main"} <= found


def _run(code: str, tmp_path: Path) -> dict:
    result = subprocess.run(
        [sys.executable, "-c", code],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
        env={"PATH": "/usr/bin:/bin", "HOME": str(tmp_path), "VOXNERF_DATA_DIR": str(tmp_path / "data")},
    )
    assert result.returncode == 0, result.stderr
    return json.loads(result.stdout.strip().splitlines()[-1])


API_PROCESS = f"""
import json, sys
from fastapi.testclient import TestClient
from app.main import create_app

app = create_app()
with TestClient(app) as client:  # start-up included: directories, store check, database, the first sweep
    assert client.get("/openapi.json").status_code == 200
    assert client.get("/jobs").json() == []
    assert client.get("/scenes").json() == []
    bad_pose = {{"job_id": "a" * 32, "transform_matrix": [[2, 0, 0, 0]] * 4}}
    assert client.post("/render", json=bad_pose).status_code == 422
    assert client.post("/scenes/" + "a" * 32 + "/jobs", json={{"max_iters": 5}}).status_code == 404
print(json.dumps([name for name in {HEAVY_MODULES!r} if name in sys.modules]))
"""


def test_the_api_process_does_not_load_torch(tmp_path: Path):
    assert _run(API_PROCESS, tmp_path) == []


WORKER_IMPORT = """
import json, sys
from celery import _state
import worker.tasks, worker.outputs, worker.model_cache, worker.run

print(json.dumps({
    "celery_apps": len(list(_state._get_active_apps())),
    "cached_models": worker.model_cache.model_cache.cache_info().currsize,
}))
"""


def test_importing_the_workers_builds_no_celery_app_and_no_model_cache(tmp_path: Path):
    assert _run(WORKER_IMPORT, tmp_path) == {"celery_apps": 0, "cached_models": 0}


def test_the_engine_keeps_its_modules_in_the_packages_of_its_layers():
    top = sorted(p.name for p in (ROOT / "voxnerf").glob("*.py"))
    assert len(top) <= 10, top
    packages = {p.name for p in (ROOT / "voxnerf").iterdir() if (p / "__init__.py").is_file()}
    assert {"data", "cameras", "prior", "model", "training", "inference"} <= packages
