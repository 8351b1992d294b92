"""`combined-reality import`: a lab recording (delimited text, Parquet, MATLAB, TDMS, MDF, CAN
log) in its own units into a run CSV, through a mapping file (docs/formats.md)."""
from __future__ import annotations

import argparse

from .. import options
from .common import add_max_rows, check_paths, eprint, progress_printer, typed


def add_parser(sub) -> argparse.ArgumentParser:
    p = sub.add_parser(
        "import", help="convert a lab recording (its own units and format) into a run CSV",
        description="Convert a lab recording into the run format (t, u, x, p1, p2 in s, 1, m, Pa absolute): the "
                    "mapping file names for each channel its source column, its unit (any unit pint knows: ms, "
                    "mm, bar, psi, kPa, V, percent, ...), whether a pressure is gauge (then [atmosphere] pressure "
                    "is added) and for the command a linear map u = (value - zero) / span. Sources: delimited text "
                    "(delimiter and decimal mark given or detected), Parquet, MATLAB .mat (v7.3 needs the mat73 "
                    "extra), TDMS (tdms extra), MDF4 (mdf extra) and CAN logs decoded with a DBC. Irregular "
                    "sampling is reported; --resample puts the run on a regular grid. The written run says in "
                    "its header where it came from and how each channel was converted. Exit status 2 when the "
                    "recording or the mapping cannot give a run (the message names the line or key).")
    p.add_argument("raw", metavar="RAW", help="the recording (format from its suffix or [source] format)")
    p.add_argument("--map", required=True, metavar="MAP.toml", help="the mapping file (docs/formats.md)")
    p.add_argument("-o", "--output", required=True, metavar="RUN.csv", help="the run to write (replaced atomically)")
    p.add_argument("--resample", metavar="RATE", type=typed(options.sample_rate, "--resample"),
                   help=f"resample to RATE Hz ({options.RATE_MIN:g} to {options.RATE_MAX:g}): measurements "
                        "interpolated linearly, the command held from its last sample; instants inside gaps of lost "
                        "samples are left out")
    p.add_argument("--json", metavar="OUT.json", help="write what was done (sampling report, conversions) as JSON")
    add_max_rows(p)
    p.add_argument("-q", "--quiet", action="store_true", help="no report on stderr")
    p.set_defaults(func=run)
    return p


def run(args) -> int:
    from ..files import clean_json, write_json_atomic, write_run
    from ..importing import import_recording, load_mapping

    rate = args.resample
    check_paths({"-o": args.output, "--json": args.json}, inputs=[args.raw, args.map])
    say = progress_printer(args.quiet)
    mapping = load_mapping(args.map)  # a MappingError is bad input (exit status 2), its sentence ends in one stop
    result = import_recording(args.raw, mapping, rate, max_rows=args.max_rows)
    write_run(args.output, result.run, comments=result.comments)
    for warning in result.warnings:  # said also with -q: the run may be wrong though it was written
        eprint(f"combined-reality import: warning: {warning}.")
    if say:
        say(f"{args.raw}: {result.comments[0].split(', ', 1)[1]}")
        say(f"  {result.sampling.describe()}")
        for note in result.notes:
            say(f"  note: {note}")
        say(f"wrote {args.output}: {result.run.n} samples, {result.run.duration:.6g} s")
    if args.json:
        write_json_atomic(args.json, clean_json({
            "input": str(args.raw), "mapping": str(args.map), "output": str(args.output),
            "samples": result.run.n, "sampling": result.sampling.to_json(), "resampled_hz": rate,
            "header": list(result.comments), "notes": list(result.notes), "warnings": list(result.warnings)}))
        if say:
            say(f"wrote {args.json}")
    return 0
