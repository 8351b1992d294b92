"""Model functions compiled once and cached on disk, keyed by model structure and options.

A second process, or a second cylinder of the same structure (parameters are inputs,
never baked in), loads the shared library in milliseconds instead of rebuilding the
symbolic graph and compiling. Without a C compiler, or when compiling fails, the
functions are cached in CasADi's own serialised form (slower to run, still no rebuild).
A compiler that failed on a structure is not tried on it again (delete the cache
directory after fixing it); one installed later compiles what was stored without it.

Cache directory: $COMBINED_REALITY_CACHE, else ~/.cache/combined_reality.
Compiler: $CC, else gcc, cc or clang; CC=none uses the serialised form only.
"""
from __future__ import annotations

import functools
import hashlib
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Sequence

import casadi as ca
import numpy as np
from filelock import FileLock, Timeout

from .integrator import IntegratorOptions, StepBuilder
from .plant import Plant

CODE_REVISION = 8  # bump when generated functions change shape or meaning

# The generated code is straight-line arithmetic whose non-finite results the callers catch,
# so the compiler may reorder sums and use reciprocals, and use this host's instruction set:
# a window's sensitivities cost 11.2 ms instead of 19.0 ms (median, 2 s at 1 kHz), for results
# that differ by ~2e-12 relative. Not -ffinite-math-only: a NaN must stay a NaN to be caught.
FAST_MATH_FLAGS = ("-fno-math-errno", "-fno-signed-zeros", "-fno-trapping-math", "-fassociative-math",
                   "-freciprocal-math")
HOST_FLAGS = ("-march=native",)  # dropped where the compiler refuses it


def cache_dir() -> Path:
    env = os.environ.get("COMBINED_REALITY_CACHE")
    return Path(env) if env else Path.home() / ".cache" / "combined_reality"


def cached_model_code() -> list[Path]:
    """The model code in the cache, one file per structure: compiled (cr_KEY.so) or, where no C
    compiler worked, CasADi's serialised functions (cr_KEY.casadi)."""
    d = cache_dir()
    return sorted(p for p in d.glob("cr_*") if p.suffix in (".so", ".casadi")) if d.is_dir() else []


@functools.cache  # read once per process: every cache lookup needs it
def host_cpu() -> str:
    """What identifies this machine's instruction set: the CPU model and feature flags."""
    try:
        info = Path("/proc/cpuinfo").read_text()
    except OSError:
        return f"{platform.machine()} {platform.processor()}"
    wanted = ("model name", "flags", "Features", "CPU part")  # x86 and ARM spell them differently
    lines = {}
    for line in info.splitlines():
        name = line.split(":", 1)[0].strip()
        if name in wanted and name not in lines:
            lines[name] = line
    return hashlib.sha256("\n".join(sorted(lines.values())).encode()).hexdigest()[:16]


def _compiler() -> str | None:
    chosen = os.environ.get("CC")
    if chosen is not None:  # an explicit choice is kept, also "none"
        return chosen if chosen != "none" and shutil.which(chosen) else None
    return next((cc for cc in ("gcc", "cc", "clang") if shutil.which(cc)), None)


@dataclass
class BuildStats:
    """Where time went when the functions were obtained (cold start vs cache hit)."""

    cache_hit: bool = False
    build_s: float = 0.0
    compile_s: float = 0.0
    path: str = ""


def load_or_build(key_parts: Sequence, build: Callable[[], list[ca.Function]], names: Sequence[str],
                  progress: Callable[[str], None] | None = None) -> tuple[dict[str, ca.Function], BuildStats]:
    """Functions `names` from the cache, or build(), compile and store them."""
    # a library built for this host's instruction set must not be loaded on another (a cache
    # directory shared over the network)
    key = hashlib.sha256(repr((tuple(key_parts), CODE_REVISION, ca.__version__, sys.platform, FAST_MATH_FLAGS,
                               HOST_FLAGS, host_cpu())).encode()).hexdigest()[:20]
    d = cache_dir()
    so = d / f"cr_{key}.so"
    ser = d / f"cr_{key}.casadi"
    stats = BuildStats()
    t0 = time.perf_counter()
    failed = d / f"cr_{key}.compile_failed"
    cc = _compiler()
    found = _cached(so, ser, failed, cc, names)
    if found is None:
        # one process builds, the others wait and load its result: the workers of a batch or
        # a test session that start cold would otherwise each compile the same library
        d.mkdir(parents=True, exist_ok=True)
        lock = FileLock(d / f"cr_{key}.lock")
        try:
            lock.acquire(blocking=False)
        except Timeout:
            if progress:
                progress("another process is building these model functions; waiting for it")
            lock.acquire()
        try:
            found = _cached(so, ser, failed, cc, names)
            if found is None:
                return _build_and_store(key, build, names, d, so, ser, failed, cc, stats, t0, progress)
        finally:
            lock.release()
    stats.cache_hit, stats.path = True, found[1]
    return found[0], stats


def _cached(so: Path, ser: Path, failed: Path, cc: str | None,
            names: Sequence[str]) -> tuple[dict[str, ca.Function], str] | None:
    """The functions from the cache and the file they came from, or None."""
    if so.exists():
        try:
            return {n: ca.external(n, str(so)) for n in names}, str(so)
        except RuntimeError:
            pass  # stale or foreign library: rebuild
    # the serialised form stands in when there is no compiler, or when this one failed on this
    # structure before (not retried); a compiler installed later still gets its chance
    if ser.exists() and (cc is None or failed.exists()):
        try:
            fs = ca.Function.load(str(ser))  # a single Function holding all, see _bundle
            return {n: fs.find_function(n) for n in names}, str(ser)
        except Exception:
            pass
    return None


def _build_and_store(key: str, build: Callable[[], list[ca.Function]], names: Sequence[str], d: Path, so: Path,
                     ser: Path, failed: Path, cc: str | None, stats: BuildStats, t0: float,
                     progress: Callable[[str], None] | None) -> tuple[dict[str, ca.Function], BuildStats]:
    if progress:
        progress("building the model functions (first use of this model structure; cached afterwards)")
    funcs = build()
    stats.build_s = time.perf_counter() - t0
    if cc is not None:
        t1 = time.perf_counter()
        if progress:
            progress(f"compiling the model functions with {cc} (once, a few seconds)")
        error = _compile(funcs, key, d, so, cc)
        stats.compile_s = time.perf_counter() - t1
        if error is None:
            stats.path = str(so)
            return {n: ca.external(n, str(so)) for n in names}, stats
        failed.write_text(error + "\n")
        if progress:
            progress(f"compiling failed ({error}); using CasADi's virtual machine instead (slower)")
    tmp = ser.with_suffix(f".tmp{os.getpid()}")
    _bundle(funcs).save(str(tmp))
    os.replace(tmp, ser)
    stats.path = str(ser)
    return {f.name(): f for f in funcs}, stats


def _compile(funcs: list[ca.Function], key: str, d: Path, so: Path, cc: str) -> str | None:
    """Generate C and build the shared library; None on success, else the compiler's complaint."""
    with tempfile.TemporaryDirectory(dir=d) as tmpd:
        cname = f"cr_{key}.c"
        cg = ca.CodeGenerator(cname, {"with_header": False})
        for f in funcs:
            cg.add(f)
        cg.generate(tmpd + os.sep)
        tmp_so = Path(tmpd) / f"cr_{key}.so"
        for host in (HOST_FLAGS, ()):
            cmd = [cc, "-O2", "-fPIC", "-shared", *FAST_MATH_FLAGS, *host, str(Path(tmpd) / cname), "-o", str(tmp_so),
                   "-lm"]
            res = subprocess.run(cmd, capture_output=True, text=True)
            if res.returncode == 0:
                break
        if res.returncode != 0:
            return res.stderr.strip().splitlines()[-1][:300] if res.stderr.strip() else f"exit {res.returncode}"
        os.replace(tmp_so, so)  # atomic: concurrent processes see the old or the new file, never half
    return None


def _bundle(funcs: list[ca.Function]) -> ca.Function:
    """One serialisable Function that references all others (find_function recovers them)."""
    args, outs = [], []
    for f in funcs:
        ins = [ca.MX.sym(f"{f.name()}_{i}", f.sparsity_in(i)) for i in range(f.n_in())]
        args.extend(ins)
        outs.extend(f.call(ins))
    return ca.Function("bundle", args, outs)


class NumpyCall:
    """A CasADi function evaluated from and into dense numpy arrays.

    A DM result reaches numpy through a Python list of its elements: for the sensitivities
    of a 20 s run (about a million numbers) that took a fifth of an identification. A
    function buffer writes the results straight into arrays held here. Inputs broadcast like
    a DM call (a column fills every column). Results are fresh arrays."""

    def __init__(self, f: ca.Function):
        for i in range(f.n_in()):
            if not f.sparsity_in(i).is_dense():
                raise ValueError(f"{f.name()}: input {i} is sparse; NumpyCall needs dense inputs")
        for i in range(f.n_out()):
            if not f.sparsity_out(i).is_dense():
                raise ValueError(f"{f.name()}: output {i} is sparse; NumpyCall needs dense outputs")
        self.name = f.name()
        self._shape_in = [f.size_in(i) for i in range(f.n_in())]
        self._buffer, self._eval = f.buffer()
        # CasADi stores column-major: the transpose of a C-ordered array has that layout
        self._out = [np.empty(f.size_out(i)[::-1]) for i in range(f.n_out())]
        for i, o in enumerate(self._out):
            self._buffer.set_res(i, memoryview(o))

    def __call__(self, *args) -> list[np.ndarray]:
        if len(args) != len(self._shape_in):
            raise TypeError(f"{self.name} takes {len(self._shape_in)} inputs, got {len(args)}")
        held = []
        for i, (a, (r, c)) in enumerate(zip(args, self._shape_in)):
            a = np.asarray(a, float)
            a = a.reshape(r, -1) if a.ndim < 2 else a
            if a.shape != (r, c):
                if a.shape != (r, 1):
                    raise ValueError(f"{self.name}: input {i} has shape {a.shape}, expected ({r}, {c})")
                a = np.broadcast_to(a, (r, c))
            a = np.ascontiguousarray(a.T)
            held.append(a)  # alive until the evaluation is done
            self._buffer.set_arg(i, memoryview(a))
        self._eval()
        if self._buffer.ret() != 0:  # a DM call raises here
            raise RuntimeError(f"{self.name}: evaluation failed (return code {self._buffer.ret()})")
        # C order, as a DM call gives: the same summation order downstream, the same numbers
        return [np.ascontiguousarray(o.T) for o in self._out]


class VectorCall:
    """A CasADi function of dense inputs and one dense output, evaluated on input and output
    arrays held here: one call per sample costs the function's own time and a few copies.
    (A DM call of the virtual rig's step took 173 us, NumpyCall 42 us, the step itself 9 us.)"""

    def __init__(self, f: ca.Function):
        if f.n_out() != 1 or not all(f.sparsity_in(i).is_dense() for i in range(f.n_in())) \
                or not f.sparsity_out(0).is_dense():
            raise ValueError(f"{f.name()}: VectorCall needs dense inputs and one dense output")
        self.name = f.name()
        self._buffer, self._eval = f.buffer()
        self._in = [np.zeros(f.numel_in(i)) for i in range(f.n_in())]
        for i, a in enumerate(self._in):
            self._buffer.set_arg(i, memoryview(a))
        self._out = np.zeros(f.numel_out(0))
        self._buffer.set_res(0, memoryview(self._out))

    def __call__(self, *args) -> np.ndarray:
        """The output (a fresh flat array, column-major as CasADi stores it) for these inputs
        (each a scalar or an array of the input's size, column-major)."""
        if len(args) != len(self._in):
            raise TypeError(f"{self.name} takes {len(self._in)} inputs, got {len(args)}")
        for a, v in zip(self._in, args):
            a[...] = v
        self._eval()
        if self._buffer.ret() != 0:
            raise RuntimeError(f"{self.name}: evaluation failed (return code {self._buffer.ret()})")
        return self._out.copy()


@dataclass
class ShootingFunctions:
    """The compiled functions one drive/structure needs.

    step      (x, w0, w1, p, h) -> x_next                          one sample
    interval  (s, W[nw x M+1], p, H[1 x M]) -> X[nx x M]           states at the M next samples
    sens      (s, W, p, H) -> (X[nx x M], S[nx x M*nz])            with d X / d (s, p[free])

    A step of length h = 0 leaves the state unchanged: trajectories of any length run through
    the fixed-length interval, the last one padded with such steps (`simulate`).
    """

    plant: Plant
    interval_len: int
    free: tuple[int, ...]
    step: ca.Function
    interval: ca.Function
    sens: ca.Function | None
    stats: BuildStats = field(default_factory=BuildStats)

    def simulate(self, s0, w, p, h, rows: Sequence[int] | None = None) -> np.ndarray:
        """States (nx, n+1) at the samples 0..n of a trajectory from s0 (sample 0); with `rows`,
        only those states (the outputs of a long run, without the whole state held).

        w: inputs at the n+1 sample instants (nw, n+1), a 1-D array for a single input
        (a held input's last column is not used); h: the n step lengths, or one for all.
        Runs through `interval` M samples at a time, one compiled function for every length.
        """
        M = self.interval_len
        w = np.atleast_2d(np.asarray(w, float))
        n = w.shape[1] - 1
        K = -(-n // M)
        pad = K * M - n
        w = np.hstack([w, np.repeat(w[:, -1:], pad, axis=1)])
        h = np.concatenate([np.broadcast_to(np.asarray(h, float), (n,)), np.zeros(pad)])
        rows = list(range(self.plant.nx)) if rows is None else list(rows)
        X = np.empty((len(rows), K * M + 1))
        s = np.asarray(s0, float).ravel()
        X[:, 0] = s[rows]
        for k in range(K):
            Xk = np.asarray(self.interval(s, w[:, k * M:(k + 1) * M + 1], p, h[None, k * M:(k + 1) * M]))
            X[:, k * M + 1:(k + 1) * M + 1] = Xk[rows]
            s = Xk[:, -1]
        return X[:, :n + 1]


# columns per call of a plant function's compiled map (ColumnCall): the last chunk is padded
COLUMN_CHUNK = 1024


class ColumnCall:
    """A function whose first `n_columned` inputs are columns (states, inputs, pressures...) and
    whose other inputs are shared by every column (parameters), over many columns, through one
    compiled map of COLUMN_CHUNK columns (the last chunk padded with copies of its last
    column). A fresh CasADi map of the symbolic function per call cost 0.2 s to build and
    0.3 s to evaluate on the 20 000 samples of a 20 s run."""

    def __init__(self, call: NumpyCall, chunk: int, n_out: int, n_columned: int):
        self._call, self.chunk, self.n_out, self.n_columned = call, chunk, n_out, n_columned

    def __call__(self, *args) -> np.ndarray:
        cols = [np.atleast_2d(np.asarray(a, float)) for a in args[:self.n_columned]]
        shared = args[self.n_columned:]
        n = cols[0].shape[1]
        if any(c.shape[1] != n for c in cols):
            raise ValueError(f"columns of unequal length: {[c.shape[1] for c in cols]}")
        out = np.empty((self.n_out, n))
        for a in range(0, n, self.chunk):
            b = min(a + self.chunk, n)
            part = [c[:, a:b] for c in cols]
            if b - a < self.chunk:
                part = [np.pad(c, ((0, 0), (0, self.chunk - (b - a))), mode="edge") for c in part]
            out[:, a:b] = self._call(*part, *shared)[0][:, :b - a]
        return out


def compiled_columns(f: ca.Function, name: str, key_parts: Sequence, n_columned: int,
                     progress=None) -> ColumnCall:
    """f (first `n_columned` inputs per column, the rest shared; one output) over many columns,
    compiled once and cached on disk under `key_parts` (what determines f's structure)."""

    def build() -> list[ca.Function]:
        return [f.map(name, "serial", COLUMN_CHUNK, list(range(n_columned, f.n_in())), [])]

    fns, _ = load_or_build(("columns", *key_parts, COLUMN_CHUNK), build, [name], progress)
    return ColumnCall(NumpyCall(fns[name]), COLUMN_CHUNK, f.size1_out(0), n_columned)


def plant_columns(plant: Plant, which: str = "rhs", progress=None) -> ColumnCall:
    """`plant.<which>` ("rhs" or "friction") of (state, input) columns with one parameter
    vector, compiled once per plant structure and cached on disk like the shooting functions."""
    return compiled_columns(getattr(plant, which), f"{which}_cols_{plant.drive}_{plant.structure_key}_{COLUMN_CHUNK}",
                            (plant.structure_key, plant.drive, which), 2, progress)


def _skipping_zero_steps(f: ca.Function, name: str) -> ca.Function:
    """f(x, w0, w1, p, h, *carried) -> (x_next, *carried_next) with a step of length 0 (the
    padding of a short interval) short-circuited to leave everything unchanged: what the
    step computes for h = 0 anyway, without computing it."""
    sym = f.mx_in()
    hold = ca.Function(f"{name}_hold", sym, [sym[0], *sym[5:]])
    switch = ca.Function.conditional(f"{name}_switch", [hold], f)
    return ca.Function(name, sym, switch.call([sym[4] > 0, *sym]), f.name_in(), f.name_out())


def shooting_functions(plant: Plant, interval_len: int = 100, free: Sequence[int] = (),
                       opts: IntegratorOptions = IntegratorOptions(), progress=None,
                       with_sens: bool | None = None) -> ShootingFunctions:
    """`with_sens` (default: when parameters are free) builds `sens`; without free parameters
    it gives the sensitivities to the initial state alone (fitting initial states)."""
    free = tuple(int(i) for i in free)
    with_sens = bool(free) if with_sens is None else with_sens
    M = int(interval_len)
    sb = StepBuilder(plant, opts)
    nx, nw, npar = sb.nx, sb.nw, sb.npar
    tag = f"{plant.drive}_{plant.structure_key}"
    names = [f"step_{tag}", f"interval_{tag}_{M}"]
    if with_sens:
        names.append(f"sens_{tag}_{M}_{'_'.join(map(str, free))}")

    def build() -> list[ca.Function]:
        step = sb.step()
        ins = step.mx_in()
        step = ca.Function(names[0], ins, step.call(ins), ["x", "w0", "w1", "p", "h"], ["xn"])
        s = ca.MX.sym("s", nx)
        W = ca.MX.sym("W", nw, M + 1)
        p = ca.MX.sym("p", npar)
        H = ca.MX.sym("H", 1, M)
        P = ca.repmat(p, 1, M)
        acc = _skipping_zero_steps(step, "step_or_hold").mapaccum("acc", M)
        X = acc(s, W[:, :M], W[:, 1:], P, H)
        interval = ca.Function(names[1], [s, W, p, H], [X], ["s", "W", "p", "H"], ["X"])
        funcs = [step, interval]
        if with_sens:
            sstep = _skipping_zero_steps(sb.sensitivity_step(free), "sens_or_hold")
            acc_s = sstep.mapaccum("acc_s", M, [0, 5], [0, 1])
            S0 = ca.horzcat(ca.MX.eye(nx), ca.MX.zeros(nx, len(free)))
            Xs, Ss = acc_s(s, W[:, :M], W[:, 1:], P, H, S0)
            funcs.append(ca.Function(names[2], [s, W, p, H], [Xs, Ss],
                                     ["s", "W", "p", "H"], ["X", "S"]))
        return funcs

    key = ("shooting", plant.structure_key, plant.drive, opts.key(), M, free, with_sens)
    fns, stats = load_or_build(key, build, names, progress)
    return ShootingFunctions(plant, M, free, fns[names[0]], fns[names[1]], fns[names[2]] if with_sens else None, stats)
