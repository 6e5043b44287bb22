"""The layers: the learning side loads without the simulator, the dataset's schema is the one
place that says what a sample holds, and settings that must agree are derived, not defaulted."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
import torch

import e2e_lite
import e2e_lite.imitation.collector
import e2e_lite.learning.dataset
from e2e_lite.control.expert import Expert
from e2e_lite.control.tracker import default_tracker
from e2e_lite.driving.evaluation import EvalConfig, evaluate
from e2e_lite.imitation.agents import CruiseControl, SteeringAgent, TrajectoryAgent
from e2e_lite.learning.dataset import FIELDS, SCHEMA, allocate, synthetic_data
from e2e_lite.learning.models import ModelConfig, build_model
from e2e_lite.simulation.world import SimConfig, WorldConfig

SIMULATOR = ("pymunk", "cv2", "e2e_lite.control.tracker")


def test_the_learning_modules_import_without_the_simulator() -> None:
    """Issue 87: every module of learning/ loads without the simulator, and none imports
    anything of simulation/, control/, driving/ or above, at its top or in a function."""
    from pathlib import Path

    folder = Path(e2e_lite.__file__).parent / "learning"
    learning = sorted(p.stem for p in folder.glob("*.py") if p.stem != "__init__")
    assert {"labels", "dataset", "models", "losses", "training", "checkpoints"} <= set(learning)
    code = (
        "import sys\n"
        + "".join(f"import e2e_lite.learning.{m}\n" for m in learning)
        + f"print(sorted(m for m in {SIMULATOR!r} if m in sys.modules))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]", out.stdout + out.stderr
    # and the check itself can fail: the collector does pull the simulator in
    code = (
        "import sys, e2e_lite.imitation.collector\n"
        f"print(sorted(m for m in {SIMULATOR!r} if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == str(sorted(SIMULATOR))
    # what each learning module imports of the library, wherever in the file: base, stats, learning
    allowed = ("e2e_lite.learning", "e2e_lite.stats", "e2e_lite.config", "e2e_lite.artifacts")
    for name, targets in _library_imports().items():
        if name.startswith("e2e_lite.learning"):
            above = sorted(t for t in targets if not t.startswith(allowed) and t != "e2e_lite")
            assert not above, (name, above)


def test_an_evaluation_worker_imports_neither_scipy_stats_nor_python_control() -> None:
    """A shard worker unpickles a network agent (trackers already built) and drives: the p-values'
    scipy.stats and the LQR design's python-control (which loads matplotlib) are imported where
    they are used, not at the top, and cost a worker's start ~1 s when they were."""
    heavy = ("scipy.stats", "control", "matplotlib")
    code = (
        "import sys\n"
        "import e2e_lite.driving.shard_worker, e2e_lite.driving.parallel\n"
        "import e2e_lite.imitation.agents, e2e_lite.safety.agent\n"
        f"print(sorted(m for m in {heavy!r} if m in sys.modules))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]", out.stdout + out.stderr
    # the tracker still designs its gains where it is built (and imports python-control then)
    code = (
        "import sys\n"
        "from e2e_lite.control.tracker import LQRTracker\n"
        "LQRTracker()\n"
        "print('control' in sys.modules)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "True", out.stdout + out.stderr


def test_the_schema_makes_the_field_list_the_arrays_the_synthetic_data_and_the_docs() -> None:
    assert FIELDS == tuple(n for n in SCHEMA if n != "images")
    arrays = allocate(3, (4, 5), fill=0)
    assert set(arrays) == set(SCHEMA)
    assert arrays["images"].shape == (3, 4, 5, 3)
    assert arrays["trajectory"].shape == (3, 5, 2) and arrays["speed"].shape == (3,)
    syn = synthetic_data(8)
    for name, (_, dtype, meaning) in SCHEMA.items():
        assert arrays[name].dtype == dtype and syn.arrays[name].dtype == dtype, name
        assert (
            f"``{name}``" in e2e_lite.learning.dataset.__doc__
            and meaning[:20] in e2e_lite.learning.dataset.__doc__
        )
    assert syn.images.shape == (8, 66, 200, 3)
    # the collector's module re-exports the dataset's names (the chapters read them there)
    assert e2e_lite.imitation.collector.DrivingData is e2e_lite.learning.dataset.DrivingData


def _gains(tracker) -> np.ndarray:
    return tracker.gains


def test_the_trackers_are_discretised_at_the_worlds_policy_period() -> None:
    slow = SimConfig(policy_period_s=0.2)
    base, changed = Expert(), Expert(sim=slow)
    assert base.tracker.cfg.period_s == 0.1 and changed.tracker.cfg.period_s == 0.2
    assert not np.allclose(_gains(base.tracker), _gains(changed.tracker))
    model = build_model(ModelConfig(head="trajectory", fusion_width=16))
    agent = TrajectoryAgent(model, sim=slow)
    assert agent.tracker.cfg.period_s == 0.2
    assert np.allclose(_gains(agent.tracker), _gains(changed.tracker))
    steer = SteeringAgent(build_model(ModelConfig(kind="pilotnet", head="steer")), sim=slow)
    assert steer.cruise.tracker.cfg.period_s == 0.2
    assert CruiseControl(sim=slow).tracker.cfg.period_s == 0.2
    assert default_tracker().cfg.period_s == SimConfig().policy_period_s


def test_a_driver_built_for_another_policy_period_is_refused() -> None:
    world_cfg = WorldConfig()
    with pytest.raises(ValueError, match=r"sim=world_cfg\.sim"):
        evaluate(Expert(sim=SimConfig(policy_period_s=0.2)), world_cfg, EvalConfig(miles=0.01))
    # the same driver built for the world's steps drives
    res = evaluate(
        Expert(sim=world_cfg.sim), world_cfg, EvalConfig(miles=0.01, n_worlds=1), progress=False
    )
    assert res.miles > 0


def test_models_still_run_on_synthetic_batches_after_the_move() -> None:
    data = synthetic_data(4)
    batch = e2e_lite.learning.dataset.DrivingDataset(data).batch(np.arange(4))
    out = build_model(ModelConfig(head="gmm", fusion_width=16))(batch["image"], batch["speed"])
    assert torch.isfinite(out["main"]).all()


def test_recovery_views_re_express_the_labels_in_the_shifted_cars_frame() -> None:
    from e2e_lite.imitation.recovery import to_car_frame

    pts = np.array([[[7.5, 0.0], [15.0, 0.5]]])
    pose = np.array([[10.0, 2.0, 0.3]])
    assert np.allclose(to_car_frame(pts, pose, pose), pts)  # same pose: unchanged
    left = np.array([[0.0, 0.0, 0.0]])
    shifted = np.array([[0.0, 1.0, 0.0]])  # the same car 1 m to the left
    assert np.allclose(to_car_frame(pts, left, shifted), pts - [0.0, 1.0])
    turned = np.array([[0.0, 0.0, np.pi / 2]])  # turned 90 degrees left: ahead becomes right
    assert np.allclose(to_car_frame(np.array([[[1.0, 0.0]]]), left, turned), [[[0.0, -1.0]]])
    # and back again
    there = to_car_frame(pts, pose, shifted)
    assert np.allclose(to_car_frame(there, shifted, pose), pts)


# The layers, bottom to top: a module may import from its own folder and the folders below it.
# The layers, bottom to top: a module may import from its own folder and the folders below it.
# stats: counts in, results out; simulation: the world; learning: what learns, no simulator;
# control: the expert and the tracker (the expert writes learning's label format); driving: the
# closed loop and what it measures; imitation: what drives the simulator to learn; safety: the
# guarded driver; course: the course's tools (running, timing, the book, benchmarks); record:
# the numbers of record, chapter 10's drivers and what renders them (it reads the course's times);
# exercises: the checks of the exercises (they may read the record)
LAYERS = (
    "stats",
    "simulation",
    "learning",
    "control",
    "driving",
    "imitation",
    "safety",
    "course",
    "record",
    "exercises",
)
BASE = ("config", "artifacts")  # used by every layer


def _library_imports() -> dict[str, set[str]]:
    """Each library module's dotted name -> the library modules it imports (absolute or relative)."""
    import ast
    from pathlib import Path

    root = Path(e2e_lite.__file__).parent
    found = {}
    for path in root.rglob("*.py"):
        parts = path.relative_to(root.parent).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        package = ".".join(parts[:-1])
        targets = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                targets |= {a.name for a in node.names if a.name.startswith("e2e_lite")}
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    base = package.rsplit(".", node.level - 1)[0] if node.level > 1 else package
                    mod = f"{base}.{node.module}" if node.module else base
                else:
                    mod = node.module or ""
                if mod.startswith("e2e_lite"):
                    # "from e2e_lite.learning import recipes" imports a module of that folder
                    targets |= {f"{mod}.{a.name}" for a in node.names} | {mod}
        found[name] = targets
    return found


def _rank(module: str) -> int:
    parts = module.split(".")
    if len(parts) == 1 or parts[1] in BASE:
        return 0
    assert parts[1] in LAYERS, f"{module} is in no layer: add its folder to LAYERS"
    return 1 + LAYERS.index(parts[1])


def _upward(imports: dict[str, set[str]]) -> list[str]:
    """Every import of ``imports`` that runs up a layer."""
    return sorted(
        f"{m} imports {t}"
        for m, targets in imports.items()
        for t in targets
        if _rank(t) > _rank(m) and not (t.count(".") == 1 and t.split(".")[1] in LAYERS)
    )


def _cycle(imports: dict[str, set[str]]) -> list[str]:
    """The modules left in an import cycle ([] when a topological order exists)."""
    graph = {m: {t for t in ts if t in imports and t != m} for m, ts in imports.items()}
    done: set[str] = set()
    while len(done) < len(graph):
        ready = {m for m in graph if m not in done and graph[m] <= done}
        if not ready:
            return sorted(set(graph) - done)
        done |= ready
    return []


def test_every_library_import_points_down_a_layer() -> None:
    imports = _library_imports()
    assert "e2e_lite.learning.losses" in imports and "e2e_lite.simulation.world" in imports
    assert not _upward(imports), "\n".join(_upward(imports))
    assert not _cycle(imports), f"an import cycle among {_cycle(imports)}"
    # and the checks can fail: the statistics importing a driving module, and two modules that
    # import each other, added to the real imports, are caught
    worse = {**imports, "e2e_lite.stats.seeds": {"e2e_lite.driving.metrics"}}
    assert _upward(worse) == ["e2e_lite.stats.seeds imports e2e_lite.driving.metrics"]
    looped = {**imports, "e2e_lite.driving.metrics": {"e2e_lite.driving.rollout"}}
    looped["e2e_lite.driving.rollout"] = imports["e2e_lite.driving.rollout"] | {
        "e2e_lite.driving.metrics"
    }
    assert set(_cycle(looped)) >= {"e2e_lite.driving.metrics", "e2e_lite.driving.rollout"}


def test_the_statistics_import_no_driving_and_write_no_sentence() -> None:
    """Issue 87: :mod:`e2e_lite.stats` takes counts and miles and returns frozen results; it
    imports nothing above the base (no simulator, driving, learning or record module) and holds no
    English sentence: its strings are field values, docstrings and error messages."""
    import ast
    import dataclasses
    from pathlib import Path

    import e2e_lite.stats.power
    import e2e_lite.stats.rates
    import e2e_lite.stats.seeds

    imports = _library_imports()
    for name, targets in imports.items():
        if name.startswith("e2e_lite.stats"):
            above = {t for t in targets if _rank(t) > 0 and not t.startswith("e2e_lite.stats")}
            assert not above, (name, above)
    for path in (Path(e2e_lite.__file__).parent / "stats").glob("*.py"):
        tree = ast.parse(path.read_text())
        skip = {id(n.value) for n in ast.walk(tree) if isinstance(n, ast.Expr)}  # docstrings
        skip |= {
            id(a)
            for n in ast.walk(tree)
            if isinstance(n, ast.Raise) and n.exc is not None
            for a in ast.walk(n.exc)
        }  # error messages
        for node in ast.walk(tree):
            if isinstance(node, (ast.Constant, ast.JoinedStr)) and id(node) not in skip:
                if isinstance(node, ast.JoinedStr) or isinstance(node.value, str):
                    text = ast.unparse(node)
                    assert text.count(" ") < 2, f"{path.name}: a sentence {text!r}"
    for module in (e2e_lite.stats.power, e2e_lite.stats.rates, e2e_lite.stats.seeds):
        for obj in vars(module).values():
            if dataclasses.is_dataclass(obj) and obj.__module__ == module.__name__:
                assert obj.__dataclass_params__.frozen, obj


def test_no_library_file_is_longer_than_500_lines() -> None:
    from pathlib import Path

    root = Path(e2e_lite.__file__).parent
    long = {p.name: n for p in root.rglob("*.py") if (n := len(p.read_text().splitlines())) > 500}
    assert not long, long


def test_the_readme_layout_names_every_library_file_in_its_folder() -> None:
    """The README's layout section lists each folder and file of the library, indented under its
    folder, and nothing that is not there."""
    import re
    from pathlib import Path

    root = Path(e2e_lite.__file__).parent
    readme = (root.parent / "README.md").read_text()
    layout = readme.split("## Layout", 1)[1].split("```")[1]
    listed, folder = set(), ""
    for line in layout.splitlines():
        m = re.match(r"^( {2,4})([a-z_]+(?:\.py|/))\s", line + " ")
        if not m:
            continue
        depth, name = len(m.group(1)), m.group(2)
        if depth == 2:
            folder = name if name.endswith("/") else ""
            if not name.endswith("/"):
                listed.add(name)
        else:
            listed.add(folder + name)
    present = {
        str(p.relative_to(root))
        for p in root.rglob("*.py")
        if p.name != "__init__.py" and "__pycache__" not in p.parts
    }
    assert listed == present, (sorted(listed - present), sorted(present - listed))


def test_every_lab_script_imports_what_exists() -> None:
    """A lab script whose helper left the tree leaves with it (each runs at its note's commit):
    the top-level name of every module a script of lab/ imports at its top level is installed, or
    is a script beside it (a removed name inside a package, or an import inside a function, is
    not checked). The check can fail: a script importing a removed sibling is found."""
    import ast
    import importlib.util
    from pathlib import Path

    lab = Path(__file__).resolve().parents[1] / "lab"

    def missing(source: str) -> list[str]:
        names = []
        for node in ast.parse(source).body:
            if isinstance(node, ast.Import):
                names += [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names.append(node.module)
        tops = {n.split(".")[0] for n in names}
        return sorted(
            t
            for t in tops
            if not (lab / f"{t}.py").exists() and importlib.util.find_spec(t) is None
        )

    assert missing("from labellers import Lateral\nimport numpy\n") == ["labellers"]
    found = {p.name: missing(p.read_text()) for p in sorted(lab.glob("*.py"))}
    assert found and not any(found.values()), {k: v for k, v in found.items() if v}
