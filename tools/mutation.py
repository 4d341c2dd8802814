"""Mutation testing of the code that decides safety (issue 46, points 2-3): does a test fail
when that code is changed a little?

    python tools/mutation.py                          # every group (~1.5 h on 2 busy cores)
    python tools/mutation.py --groups checks --check  # the judge alone (~4.5 min)
    python tools/mutation.py --groups c --markdown table.md

Groups (each against its fast tests, never the slow scenario runs):

- ``checks``: ``swarm/runs/checks.py`` and ``swarm/runs/network.py``, the invariant checks
  every run is judged by, against ``tests/runs/test_checks.py`` and
  ``tests/runs/test_network_checks.py``;
- ``watch``: the watchers of ``swarm/watch/`` against ``tests/watch``;
- ``core``: the readable rows of ``swarm/core`` (barrier, safety, qp, smooth_min,
  perception) against ``tests/core``;
- ``c``: hand-written mutants of the compiled kernels (``swarm/core/_kernels.c``; mutmut
  mutates Python only), each built and run against ``tests/core``.

The Python groups use mutmut (3.x): it rewrites every function of a module into a
trampoline that runs the original or one mutant, learns once which tests call which
function, and runs only those tests per mutant, in processes forked from a warm pytest. So a
mutant costs its few tests, not a pytest start, and the judge fits in CI; cosmic-ray (the other
maintained tool) starts the test command afresh for every mutant. mutmut 3 does not mutate
module-level constants (only code inside functions).

Everything runs in a copy of the tree (the files git tracks or would add, as they are now)
under ``--workdir`` (default: a temporary directory), with the extensions compiled there, so
the working tree is never touched. A surviving mutant is either killed by a new test or argued
equivalent in ``tools/mutation_equivalents.toml`` (matched by module, function and the
changed lines, so the list outlives unrelated edits). ``--check`` exits 1 if any survivor is
not argued there (or a C mutant survives or no longer applies). The table (module, mutants,
killed, survived, argued equivalent, time) is printed and, with ``--markdown``, written.
Exit 2: bad command line, or a tree that cannot be mutated (one line).
"""

from __future__ import annotations

import os
import re
import shlex
import shutil
import subprocess
import sys
import sysconfig
import tempfile
import time
import tomllib
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from swarm.errors import EXIT_FAILED, EXIT_OK, UsageError, run_main
from swarm.scenario.cli_common import OneLineParser

ROOT = Path(__file__).resolve().parent.parent
EQUIVALENTS = Path(__file__).resolve().with_name("mutation_equivalents.toml")
# Tests that run a swarm of processes or against the wall clock are not "fast tests".
FAST = ("-m", "not slow and not wallclock")


class MutationError(UsageError, RuntimeError):
    """A tree that cannot be mutation-tested (no mutmut, a failing clean test run, a C build
    that fails); one line. Exit 2 (the tree given cannot be judged), apart from ``--check``'s
    1 (judged, and a survivor is unexplained)."""


@dataclass(frozen=True)
class PythonGroup:
    """Modules mutated by mutmut against a test selection (pytest arguments)."""

    name: str
    modules: tuple[str, ...]
    tests: tuple[str, ...]


@dataclass(frozen=True)
class CMutant:
    """One hand-written change of a C source: ``original`` (found exactly once) → ``mutant``."""

    name: str
    what: str
    original: str
    mutant: str
    source: str = "swarm/core/_kernels.c"


PYTHON_GROUPS = (
    PythonGroup("checks", ("swarm/runs/checks.py", "swarm/runs/network.py"),
                ("tests/runs/test_checks.py", "tests/runs/test_network_checks.py")),
    PythonGroup("watch", ("swarm/models/command_reference.py",
                          "swarm/watch/localization_watch.py", "swarm/watch/vehicle_watch.py"),
                ("tests/watch", "tests/models/test_command_reference.py", *FAST)),
    PythonGroup("core", tuple(f"swarm/core/{m}.py" for m in
                              ("barrier", "safety", "qp", "qp_daqp", "qp_piqp",
                               "smooth_min", "perception")),
                ("tests/core", *FAST)),
)

# The compiled kernels, one change each in the terms the safety rows are built from.
C_MUTANTS = (
    CMutant("weight_gradient_sign", "perception: ∂w_D/∂d̂ below d_min with the wrong sign",
            "dw_d = -2.0 * gap / k[K_SDMIN] * w_d;", "dw_d = 2.0 * gap / k[K_SDMIN] * w_d;"),
    CMutant("off_axis_cosine", "perception: the camera looks up (cos = +β̂_z)",
            "double cos_off_axis = -bz;", "double cos_off_axis = bz;"),
    CMutant("eigen_order", "symmetric_eigen: eigenvalues sorted descending",
            "j > 0 && a[order[j]][order[j]] < a[order[j - 1]][order[j - 1]]",
            "j > 0 && a[order[j]][order[j]] > a[order[j - 1]][order[j - 1]]"),
    CMutant("eigen_one_sweep", "symmetric_eigen: one Jacobi sweep only",
            "sweep < 50 && !converged", "sweep < 1 && !converged"),
    CMutant("eigenvalue_floor", "smooth_min: λ_0 clipped from above instead of below",
            "double l0 = raw[0] > lim.floor ? raw[0] : lim.floor;",
            "double l0 = raw[0] < lim.floor ? raw[0] : lim.floor;"),
    CMutant("hessian_cross_term", "smooth_min: ∂²λ̄/∂λ_0∂λ_1 with the wrong sign",
            "out[S_HESS + 3] = one_minus_p * (g0 * g1) / value;",
            "out[S_HESS + 3] = pm1 * (g0 * g1) / value;"),
    CMutant("near_repeated_theta", "divided_difference: g_k for g_l near repeated eigenvalues",
            "return g_l / lam_l * ratio;", "return g_k / lam_l * ratio;"),
    CMutant("barrier_drift_sign", "localization_barrier: the drift term added, not subtracted",
            "out[B_LOWER] = -(coupling + psi1) / b.n_agents - drift;",
            "out[B_LOWER] = -(coupling + psi1) / b.n_agents + drift;"),
    CMutant("barrier_forgetting", "localization_barrier: the forgetting factor left out",
            "double coupling = second + (1.0 - b.forgetting) * along_rate;",
            "double coupling = second + along_rate;"),
    CMutant("negative_slack", "qp_max_violation: a negative slack is not a violation",
            "if (0.0 - z[i] > worst) worst = 0.0 - z[i];", "if (z[i] > worst) worst = z[i];"),
)
C_TESTS = ("tests/core", *FAST, "-x")
GROUPS = ("checks", "watch", "core", "c")

# The extensions of pyproject.toml's [[tool.setuptools.ext-modules]]: (source, numpy headers).
EXTENSIONS = (("swarm/core/_kernels.c", True), ("swarm/messages/_wire.c", False),
              ("swarm/agent/_exchange.c", False), ("swarm/mavlink/_frame.c", False))
C_FLAGS = ("-O2", "-std=c11", "-shared", "-fPIC")

KILLED = {"killed", "timeout", "segfault", "crashed"}  # the tests failed, hung or crashed
# on the mutant; "crashed": the test process died of a signal mutmut has no name for (it
# says "suspicious"), e.g. SIGABRT when a solver fed a mutated argument corrupts its heap.
SURVIVED = {"survived", "no tests"}  # "no tests": no selected test runs that function


# -- the tree to mutate -------------------------------------------------------------------


def copy_tree(destination: Path) -> None:
    """The files git tracks or would add (as they are now, modification times kept)."""
    listed = subprocess.run(
        ["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"], cwd=ROOT,
        check=True, capture_output=True).stdout.decode().split("\0")
    for name in filter(None, listed):
        source = ROOT / name
        if source.is_file():
            target = destination / name
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(source, target)


def build_extension(tree: Path, source: str, numpy_headers: bool) -> None:
    """Compile ``tree/source`` beside itself, as ``pip install -e .`` does."""
    compiler = shlex.split(sysconfig.get_config_var("CC") or "cc")
    includes = [f"-I{sysconfig.get_paths()['include']}"]
    if numpy_headers:
        import numpy
        includes.append(f"-I{numpy.get_include()}")
    path = tree / source
    output = path.with_name(path.stem + sysconfig.get_config_var("EXT_SUFFIX"))
    result = subprocess.run([*compiler, *C_FLAGS, *includes, str(path), "-lm", "-o", str(output)],
                            capture_output=True, text=True)
    if result.returncode != 0:
        first = (result.stderr.strip().splitlines() or ["no output"])[0]
        raise MutationError(f"building {source} failed: {first}")


# -- the Python groups (mutmut) -----------------------------------------------------------


@dataclass
class ModuleResult:
    module: str
    statuses: Counter[str] = field(default_factory=Counter)
    test_time_s: float = 0.0  # the mutants' test runs, added up
    survivors: list[Survivor] = field(default_factory=list)

    @property
    def mutants(self) -> int:
        return sum(self.statuses.values())

    @property
    def killed(self) -> int:
        return sum(self.statuses[s] for s in KILLED)


@dataclass(frozen=True)
class Survivor:
    name: str  # mutmut's, e.g. swarm.runs.checks.x__crossing__mutmut_19
    function: str  # e.g. _crossing, LocalizationWatch.update
    original: str  # the changed lines, stripped, one a line
    mutant: str
    why: str | None  # the argument that it is equivalent, None: unexplained


def mutmut_config(group: PythonGroup) -> str:
    """The [tool.mutmut] table of a group: the whole package copied (so that its imports and
    compiled extensions resolve in mutmut's mutants/ copy), only the group's modules mutated,
    pytest in one process (the project's addopts ask for xdist workers)."""
    def array(values: Sequence[str]) -> str:
        return "[" + ", ".join(f'"{v}"' for v in values) + "]"
    return (f"\n[tool.mutmut]\nsource_paths = {array(['swarm'])}\n"
            f"only_mutate = {array(group.modules)}\n"
            f"also_copy = {array(['sim_world', 'configs'])}\n"
            f"pytest_add_cli_args = {array(['-n', '0', '-p', 'no:cacheprovider'])}\n"
            f"pytest_add_cli_args_test_selection = {array(group.tests)}\n")


# mutmut's command line as its console script runs it (``python -m mutmut`` imports its
# __main__ twice and says so).
MUTMUT = "import sys; from mutmut.__main__ import cli; sys.argv[0] = 'mutmut'; sys.exit(cli())"


def mutmut(tree: Path, *args: str, log: Path | None = None) -> str:
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    with open(log, "w") if log else open(os.devnull, "w") as sink:
        result = subprocess.run([sys.executable, "-c", MUTMUT, *args], cwd=tree, env=env,
                                stdout=subprocess.PIPE if log is None else sink,
                                stderr=subprocess.STDOUT, text=True)
    if result.returncode != 0:
        where = f"; its output is in {log}" if log else f": {result.stdout.strip()[-300:]}"
        raise MutationError(f"mutmut {args[0]} exited with {result.returncode}{where}")
    return result.stdout or ""


def function_of(name: str) -> tuple[str, str]:
    """(module, function) of a mutmut mutant name; a method as Class.method."""
    module, _, mangled = name.rpartition(".")
    mangled = re.sub(r"__mutmut_\d+$", "", mangled)
    if mangled.startswith("xǁ"):
        return module, ".".join(mangled[2:].split("ǁ"))
    return module, mangled.removeprefix("x_")


def changed_lines(diff: str) -> tuple[str, str]:
    """The removed and the added lines of a unified diff, stripped, one a line."""
    lines = diff.splitlines()
    body = [line for line in lines if not line.startswith(("---", "+++", "@@", "#"))]
    removed = "\n".join(line[1:].strip() for line in body if line.startswith("-"))
    added = "\n".join(line[1:].strip() for line in body if line.startswith("+"))
    return removed, added


@dataclass(frozen=True)
class Equivalent:
    module: str
    function: str
    original: str
    mutant: str
    why: str


def load_equivalents(path: Path = EQUIVALENTS) -> list[Equivalent]:
    if not path.exists():
        return []
    try:
        entries = tomllib.loads(path.read_text())["equivalent"]
        return [Equivalent(e["module"], e["function"], e["original"].strip(),
                           e["mutant"].strip(), e["why"]) for e in entries]
    except (tomllib.TOMLDecodeError, KeyError, TypeError) as exc:
        raise MutationError(f"{path.name}: not a list of [[equivalent]] with module, function, "
                            f"original, mutant and why ({exc})") from exc


def run_python_group(group: PythonGroup, base: Path, workdir: Path, max_children: int,
                     equivalents: list[Equivalent]) -> tuple[list[ModuleResult], float]:
    tree = workdir / group.name
    shutil.copytree(base, tree, copy_function=shutil.copy2)
    pyproject = tree / "pyproject.toml"
    if "[tool.mutmut]" in pyproject.read_text():
        raise MutationError("pyproject.toml has a [tool.mutmut] table: this tool writes its own")
    with open(pyproject, "a") as f:
        f.write(mutmut_config(group))
    start = time.monotonic()
    mutmut(tree, "run", "--max-children", str(max_children), log=workdir / f"{group.name}.log")
    wall_s = time.monotonic() - start
    results = {m: ModuleResult(m.removesuffix(".py").replace("/", ".")) for m in group.modules}
    by_module = {r.module: r for r in results.values()}
    for line in mutmut(tree, "results", "--all", "true").splitlines():
        name, _, status = line.strip().rpartition(": ")
        if not name:
            continue
        module, function = function_of(name)
        result = by_module[module]
        if status == "suspicious" and (exit_code(tree, module, name) or 0) < 0:
            status = "crashed"
        result.statuses[status] += 1
        if status in SURVIVED:
            original, mutant = changed_lines(mutmut(tree, "show", name))
            why = next((e.why for e in equivalents if (e.module, e.function, e.original,
                        e.mutant) == (module, function, original, mutant)), None)
            result.survivors.append(Survivor(name, function, original, mutant, why))
    for result in results.values():
        result.test_time_s = module_test_time(tree, result.module)
    return list(results.values()), wall_s


def exit_code(tree: Path, module: str, name: str) -> int | None:
    """The exit code mutmut recorded for a mutant's test run (negative: killed by that signal)."""
    import json

    meta = tree / "mutants" / (module.replace(".", "/") + ".py.meta")
    if not meta.exists():
        return None
    code = json.loads(meta.read_text())["exit_code_by_key"].get(name)
    return code if isinstance(code, int) else None


def module_test_time(tree: Path, module: str) -> float:
    """The seconds of test runs mutmut measured for a module's mutants, added up."""
    import json
    meta = tree / "mutants" / (module.replace(".", "/") + ".py.meta")
    if not meta.exists():
        return 0.0
    return float(sum(v for v in json.loads(meta.read_text())["durations_by_key"].values()
                     if v is not None))


# -- the C group (hand-written mutants) ---------------------------------------------------


@dataclass(frozen=True)
class CResult:
    mutant: CMutant
    status: str  # killed, survived, stale (its original text is not found once)
    time_s: float


def run_c_group(base: Path, workdir: Path) -> tuple[list[CResult], float]:
    tree = workdir / "c"
    shutil.copytree(base, tree, copy_function=shutil.copy2)
    env = {**os.environ, "PYTHONPATH": str(tree)}
    out = []
    start = time.monotonic()
    for mutant in C_MUTANTS:
        path = tree / mutant.source
        pristine = (base / mutant.source).read_text()
        t0 = time.monotonic()
        if pristine.count(mutant.original) != 1:
            out.append(CResult(mutant, "stale", 0.0))
            continue
        path.write_text(pristine.replace(mutant.original, mutant.mutant))
        build_extension(tree, mutant.source, numpy_headers=True)
        tests = subprocess.run([sys.executable, "-m", "pytest", "-q", "-n", "0",
                                "-p", "no:randomly", "-p", "no:cacheprovider", *C_TESTS],
                               cwd=tree, env=env, capture_output=True, text=True)
        if tests.returncode not in (0, 1):  # 2-5: the run itself broke, not a test
            raise MutationError(f"C mutant {mutant.name}: pytest exited with "
                                f"{tests.returncode}: {tests.stdout.strip()[-300:]}")
        out.append(CResult(mutant, "killed" if tests.returncode == 1 else "survived",
                           time.monotonic() - t0))
    return out, time.monotonic() - start


# -- the table ----------------------------------------------------------------------------


def table(python: list[tuple[str, list[ModuleResult], float]],
          c: tuple[list[CResult], float] | None) -> list[str]:
    rows = ["| group | module | mutants | killed | survived | argued equivalent | killed % "
            "| time |", "|---|---|---:|---:|---:|---:|---:|---:|"]
    for group, results, wall_s in python:
        for r in results:
            survived = len(r.survivors)
            argued = sum(s.why is not None for s in r.survivors)
            share = 100.0 * r.killed / r.mutants if r.mutants else float("nan")
            rows.append(f"| {group} | `{r.module}` | {r.mutants} | {r.killed} | {survived} | "
                        f"{argued} | {share:.1f} | {r.test_time_s:.0f} s of tests |")
        rows.append(f"| {group} | (all) | {sum(r.mutants for r in results)} | "
                    f"{sum(r.killed for r in results)} | "
                    f"{sum(len(r.survivors) for r in results)} | "
                    f"{sum(s.why is not None for r in results for s in r.survivors)} | | "
                    f"{wall_s:.0f} s wall |")
    if c is not None:
        results, wall_s = c
        killed = sum(r.status == "killed" for r in results)
        rows.append(f"| c | `swarm/core/_kernels.c` (hand-written) | {len(results)} | {killed} | "
                    f"{sum(r.status == 'survived' for r in results)} | 0 | "
                    f"{100.0 * killed / len(results):.1f} | {wall_s:.0f} s wall |")
    return rows


def problems(python: list[tuple[str, list[ModuleResult], float]],
             c: tuple[list[CResult], float] | None) -> list[str]:
    """Each unexplained survivor (and each C mutant that survived or no longer applies), one
    line a problem; and the other statuses mutmut may give (not checked, suspicious)."""
    out = []
    for _group, results, _ in python:
        for r in results:
            for s in r.survivors:
                if s.why is None:
                    out.append(f"unexplained survivor {s.name} ({s.function}): "
                               f"{s.original!r} -> {s.mutant!r}")
            for status, n in r.statuses.items():
                if status not in KILLED | SURVIVED:
                    out.append(f"{r.module}: {n} mutants {status}")
    if c is not None:
        for result in c[0]:
            if result.status != "killed":
                out.append(f"C mutant {result.mutant.name} {result.status}: {result.mutant.what}")
    return out


def stale_equivalents(python: list[tuple[str, list[ModuleResult], float]],
                      equivalents: list[Equivalent]) -> list[Equivalent]:
    """Entries of the mutated modules that matched no survivor (killed now, or code changed)."""
    modules = {r.module for _, results, _ in python for r in results}
    matched = {(r.module, s.function, s.original, s.mutant)
               for _, results, _ in python for r in results for s in r.survivors}
    return [e for e in equivalents if e.module in modules
            and (e.module, e.function, e.original, e.mutant) not in matched]


def main(argv: Sequence[str] | None = None) -> int:
    parser = OneLineParser(prog="mutation", description=__doc__.split("\n\n")[0])
    parser.add_argument("--groups", default=",".join(GROUPS),
                        help=f"comma-separated, of {', '.join(GROUPS)} (default: all)")
    parser.add_argument("--max-children", type=int, default=os.cpu_count() or 1,
                        help="mutants tested at once (default: the CPUs)")
    parser.add_argument("--workdir", type=Path, help="where the copies go (default: a temporary "
                        "directory, removed at the end); kept if given, for `mutmut browse`")
    parser.add_argument("--markdown", type=Path, help="also write the table here")
    parser.add_argument("--check", action="store_true",
                        help="exit 1 on an unexplained survivor")
    args = parser.parse_args(argv)
    groups = [g.strip() for g in args.groups.split(",") if g.strip()]
    unknown = sorted(set(groups) - set(GROUPS))
    if unknown or not groups or args.max_children < 1:
        parser.error(f"--groups takes {', '.join(GROUPS)}; --max-children >= 1"
                     + (f" (not {', '.join(unknown)})" if unknown else ""))
    if args.workdir is not None and args.workdir.exists() and any(args.workdir.iterdir()):
        parser.error(f"--workdir {args.workdir} is not empty")
    workdir = args.workdir or Path(tempfile.mkdtemp(prefix="vigil-mutation-"))
    try:
        return run_main("mutation", lambda: run(groups, workdir, args.max_children,
                                                args.markdown, args.check))
    finally:
        if args.workdir is None:
            shutil.rmtree(workdir, ignore_errors=True)


def run(groups: list[str], workdir: Path, max_children: int, markdown: Path | None,
        check: bool) -> int:
    try:
        import mutmut  # noqa: F401  (the dev extra installs it)
    except ImportError as exc:
        raise MutationError("mutmut is not installed: pip install -e '.[dev]'") from exc
    equivalents = load_equivalents()
    base = workdir / "tree"
    copy_tree(base)
    for source, numpy_headers in EXTENSIONS:
        build_extension(base, source, numpy_headers)
    python = []
    for group in PYTHON_GROUPS:
        if group.name in groups:
            print(f"mutation: {group.name} ({', '.join(group.modules)})", flush=True)
            results, wall_s = run_python_group(group, base, workdir, max_children, equivalents)
            python.append((group.name, results, wall_s))
    c = None
    if "c" in groups:
        print(f"mutation: c ({len(C_MUTANTS)} hand-written mutants of the kernels)", flush=True)
        c = run_c_group(base, workdir)
    rows = table(python, c)
    print("\n".join(rows))
    for group, results, _ in python:
        for r in results:
            for s in r.survivors:
                label = f"equivalent: {s.why}" if s.why else "UNEXPLAINED"
                print(f"  {group} {s.name}: {s.original!r} -> {s.mutant!r} ({label})")
    if c is not None:
        for result in c[0]:
            print(f"  c {result.mutant.name}: {result.status} ({result.mutant.what}, "
                  f"{result.time_s:.0f} s)")
    for e in stale_equivalents(python, equivalents):
        print(f"  note: no survivor matches the equivalent {e.module} {e.function}: "
              f"{e.mutant!r} (killed now, or the code changed: remove it)")
    if markdown is not None:
        markdown.write_text("\n".join(rows) + "\n")
    found = problems(python, c)
    for line in found:
        print(f"mutation: {line}", file=sys.stderr)
    return EXIT_FAILED if check and found else EXIT_OK


if __name__ == "__main__":
    sys.exit(main())
