"""The batch manifest: which cylinders to identify, from which runs (or simulated by the
virtual rig), with which friction model. A manifest that cannot be read as a whole is
refused with one sentence (ManifestError); a bad file of one cylinder fails only its row.
The files a manifest names must lie in its own folder (or below) unless the user allows
others: a manifest from elsewhere cannot make the batch read, and quote, any file."""
from __future__ import annotations

import functools
import hashlib
import json
import os
import tomllib
from dataclasses import asdict, dataclass, replace
from pathlib import Path

from sim.inputs import InputFileError, decode_text, parse_toml, read_bounded, regular_file_size, shorten

from .. import options
from ..errors import InputError
from ..friction import DYNAMIC_SPECS, check_model

__all__ = ["MODELS_HELP", "MAX_SIMULATED_SAMPLES", "ManifestError", "SimulateSpec", "CylinderJob", "load_manifest",
           "file_stem"]


MODELS_HELP = "nominal (the cylinder file's Fc + Fv v + kp |dp|) or a friction model of the family"
# samples a cylinder's simulated runs may hold in all (duration x rate x runs): 1000 s at 1 kHz.
# Identification keeps sensitivities per sample, so memory grows with it; the papers' runs are 20 s.
MAX_SIMULATED_SAMPLES = 1_000_000
MANIFEST_MAX_BYTES = 16 << 20  # a manifest of tens of thousands of cylinders


class ManifestError(InputError):
    """The manifest cannot be read as a whole (its rows cannot even be listed): exit status 2."""


@dataclass(frozen=True)
class SimulateSpec:
    """Runs made by the virtual rig: `runs` runs of `duration` s with seeds seed, seed+1, ...,
    with `effects` (effect words or a friction model, 'name:k=v,...') as the truth."""

    duration: float = 20.0
    seed: int = 1
    effects: tuple[str, ...] = ()
    runs: int = 1
    rate: float = 1000.0
    noise: bool = True


@dataclass(frozen=True)
class CylinderJob:
    name: str
    config: str  # absolute path
    runs: tuple[str, ...] = ()  # absolute paths
    simulate: SimulateSpec | None = None
    model: str = "nominal"
    diagnose: bool = False
    max_rows: int = options.MAX_ROWS  # the run reader's limit of a run file's lines
    # the name in file names (simulated runs, cache entries): unique in the manifest, also where two
    # names differ only in characters a file name cannot hold or in case
    file_stem: str = ""

    @property
    def stem(self) -> str:
        """The name in file names (the manifest's unique one, else the name made safe)."""
        return self.file_stem or file_stem(self.name)

    def content_hash(self) -> str:
        """Everything the row depends on; a missing file hashes as missing (and fails)."""
        h = hashlib.sha256()
        recipe = {"code": _code_fingerprint(), "name": self.name, "model": self.model,
                  "diagnose": self.diagnose, "simulate": asdict(self.simulate) if self.simulate else None}
        h.update(json.dumps(recipe, sort_keys=True).encode())
        for p in (self.config, *self.runs):
            h.update(b"\0" + Path(p).name.encode() + b"\0")
            try:
                regular_file_size(p, "an input")  # a FIFO would block, a device never end
                with open(p, "rb") as f:
                    while block := f.read(1 << 20):
                        h.update(block)
            except (OSError, InputFileError):
                h.update(b"missing")
        return h.hexdigest()[:24]


@functools.lru_cache(maxsize=1)
def _code_fingerprint() -> str:
    """The source of the model, rig and application packages: a row computed by other code is
    not reused (an upgrade, a fix of the identification)."""
    import hw
    import sim

    h = hashlib.sha256()
    for pkg in (Path(sim.__file__).parent, Path(hw.__file__).parent, Path(__file__).parent.parent):
        for f in sorted(pkg.rglob("*.py")):
            h.update(f.relative_to(pkg).as_posix().encode() + b"\0" + f.read_bytes())
    return h.hexdigest()[:16]


_CYLINDER_KEYS = {"name", "config", "runs", "simulate", "model"}


_SIMULATE_KEYS = {"duration", "seed", "effect", "runs", "rate", "noise"}


def file_stem(name: str) -> str:
    """A cylinder's name as it can stand in a file name on any system."""
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in name).strip(".")[:80] or "cylinder"


def _unique_stems(names: list[str]) -> list[str]:
    """file_stem of each name; names whose stems collide (also by case: macOS and Windows file
    systems ignore it) get a short hash of the exact name, so that the stems stay the same
    however the manifest is reordered."""
    stems = [file_stem(n) for n in names]
    counts: dict[str, int] = {}
    for st in stems:
        counts[st.lower()] = counts.get(st.lower(), 0) + 1
    return [st if counts[st.lower()] == 1 else f"{st}-{hashlib.sha256(n.encode()).hexdigest()[:6]}"
            for n, st in zip(names, stems)]


def load_manifest(path: str | os.PathLike[str], diagnose: bool = False, allow_outside: bool = False,
                  max_rows: int = options.MAX_ROWS) -> list[CylinderJob]:
    """The manifest's cylinders as jobs. Structural faults (TOML syntax, a missing name, an
    unknown key, duplicate names, an unknown model, a file outside the manifest's folder
    without `allow_outside`) raise ManifestError with one sentence; files that are missing
    or bad fail their own row later, not the batch."""
    path = Path(path)
    try:
        doc = parse_toml(decode_text(read_bounded(path, "a manifest", MANIFEST_MAX_BYTES),
                                     lambda line, _: ManifestError(f"{path}, line {line}: not UTF-8 text (a manifest "
                                                                   "is TOML, which is UTF-8).")))
    except InputFileError as e:
        raise ManifestError(str(e)) from None
    except OSError as e:
        raise ManifestError(f"cannot read the manifest {path}: {e.strerror or e}") from None
    except tomllib.TOMLDecodeError as e:
        raise ManifestError(f"{path} is not valid TOML: {e}") from None
    unknown = set(doc) - {"cylinder", "model", "simulate"}
    if unknown:
        raise ManifestError(f"{path}: unknown top-level key(s) {shorten(', '.join(sorted(unknown)))} "
                            "(expected [[cylinder]] tables, and optionally model = ... and [simulate] defaults).")
    entries = doc.get("cylinder")
    if not isinstance(entries, list) or not entries or not all(isinstance(e, dict) for e in entries):
        raise ManifestError(f"{path} lists no cylinders: add [[cylinder]] tables with name, config and runs "
                            "(or simulate).")
    default_model = doc.get("model", "nominal")
    default_sim = doc.get("simulate", {})
    if not isinstance(default_sim, dict):
        raise ManifestError(f"{path}: the top-level simulate must be a table of defaults.")
    base = path.resolve().parent

    def inside(p: str, key: str, where: str) -> str:
        full = (base / p).resolve()  # `..` and links followed: where the file really is
        if not allow_outside and not full.is_relative_to(base):
            raise ManifestError(f"{where}: {key} {shorten(repr(p))} lies outside the manifest's folder {base}; "
                                "pass --allow-outside to let a manifest name files elsewhere.")
        return str(full)

    jobs, seen = [], set()
    for i, e in enumerate(entries, 1):
        where = f"{path}, cylinder {i}"
        name = e.get("name")
        if not isinstance(name, str) or not name.strip():
            raise ManifestError(f"{where}: every cylinder needs a name (a non-empty string).")
        where = f"{path}, cylinder '{shorten(name)}'"
        if name in seen:
            raise ManifestError(f"{where}: the name is used twice; names identify rows and must be unique.")
        seen.add(name)
        bad = set(e) - _CYLINDER_KEYS
        if bad:
            raise ManifestError(f"{where}: unknown key(s) {shorten(', '.join(sorted(bad)))} "
                                f"(known: {', '.join(sorted(_CYLINDER_KEYS))}).")
        config = e.get("config")
        if not isinstance(config, str):
            raise ManifestError(f"{where}: config must name a cylinder file.")
        model = e.get("model", default_model)
        try:
            check_model(model)
        except (ValueError, TypeError):
            raise ManifestError(f"{where}: unknown model {shorten(repr(model))} ({MODELS_HELP}: "
                                f"{', '.join(DYNAMIC_SPECS)}).") from None
        runs, sim = e.get("runs"), e.get("simulate")
        if (runs is None) == (sim is None):
            raise ManifestError(f"{where}: give either runs = [...] (recorded runs) or simulate = {{...}}, "
                                "exactly one of them.")
        if runs is not None and (not isinstance(runs, list) or not runs or not all(isinstance(r, str) for r in runs)):
            raise ManifestError(f"{where}: runs must be a non-empty list of run CSV paths.")
        spec = None
        if sim is not None:
            if not isinstance(sim, dict):
                raise ManifestError(f"{where}: simulate must be a table, e.g. {{duration = 20, seed = 1}}.")
            spec = _simulate_spec({**default_sim, **sim}, where, diagnose)
        jobs.append(CylinderJob(name=name, config=inside(config, "config", where),
                                runs=tuple(inside(r, "runs", where) for r in runs or ()),
                                simulate=spec, model=model, diagnose=diagnose, max_rows=max_rows))
    stems = _unique_stems([j.name for j in jobs])
    return [replace(j, file_stem=st) for j, st in zip(jobs, stems)]


def _simulate_spec(sim: dict, where: str, diagnose: bool) -> SimulateSpec:
    bad = set(sim) - _SIMULATE_KEYS
    if bad:
        raise ManifestError(f"{where}: unknown simulate key(s) {shorten(', '.join(sorted(bad)))} "
                            f"(known: {', '.join(sorted(_SIMULATE_KEYS))}).")
    eff = sim.get("effect", [])
    effects = tuple(eff) if isinstance(eff, list) else (eff,)
    if not all(isinstance(x, str) for x in effects):
        raise ManifestError(f"{where}: simulate.effect must be a string 'name:k=v,...' or a list of them.")
    # TOML has types: a seed of 1.5 or a duration of true is a slip, not something to round; each
    # value is held to the rule of its command-line option (combined_reality.options)
    try:
        duration = options.positive_seconds(sim.get("duration", 20.0), "simulate.duration")
        rate = options.sample_rate(sim.get("rate", 1000.0), "simulate.rate")
        seed = options.seed(sim.get("seed", 1), "simulate.seed")
        runs = options.whole_number(sim.get("runs", 2 if diagnose else 1), "simulate.runs", 1)
        options.seed(seed + runs - 1, "simulate.seed + simulate.runs - 1")  # the last run's seed
        options.simulated_samples(duration, rate, "simulate.duration")
    except options.OptionError as e:
        raise ManifestError(f"{where}: {e}") from None
    samples = duration * rate * runs
    if samples > MAX_SIMULATED_SAMPLES:
        raise ManifestError(f"{where}: simulate asks for {samples:.3g} samples (duration {duration:g} s x rate "
                            f"{rate:g} Hz x {runs} run(s)); at most {MAX_SIMULATED_SAMPLES:.0e} per cylinder "
                            f"(e.g. {MAX_SIMULATED_SAMPLES / rate / runs:g} s at this rate), which identifies "
                            "friction many times over.")
    noise = sim.get("noise", True)
    if not isinstance(noise, bool):
        raise ManifestError(f"{where}: simulate.noise must be true or false.")
    return SimulateSpec(duration=duration, seed=seed, effects=effects, runs=runs, rate=rate, noise=noise)
