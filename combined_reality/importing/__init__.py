"""`import`: lab recordings in their own units and formats into runs (docs/formats.md, "The
mapping file").

- mapping: the mapping file (which column is which channel, its unit, gauge, the command's map)
- units: unit conversion through pint
- delimited, parquet, matlab, tdms, mdf, canlog: one reader per source format, each through its
  established library (npTDMS, asammdf and h5py are optional extras)
- raw: what readers return; channels on their own time bases aligned onto the rows
- sampling: the sampling report and resampling onto a regular grid
- convert: the whole conversion, with the checks a run must pass
"""
from .convert import READERS, ImportResult, import_recording, reader
from .mapping import ChannelMap, ImportMapping, MappingError, SourceOptions, load_mapping, parse_mapping
from .sampling import SamplingReport, resample, sampling_report

__all__ = ["READERS", "ImportResult", "import_recording", "reader", "ChannelMap", "ImportMapping", "MappingError",
           "SourceOptions", "load_mapping", "parse_mapping", "SamplingReport", "resample", "sampling_report"]
