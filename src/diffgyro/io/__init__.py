"""Reading and writing recordings: CSV, Parquet and NPZ in the standard schema; logs.

The standard schema: ``device, t, gx, gy, gz`` plus the
optional groups ``temp``, ``temp_ext``, ``ax..az``, ``mx..mz``, ``rx..rz`` and
``qw..qz``, in SI units (s, rad/s, m/s², °C). One file may hold many devices
in long format (a ``device`` column); without it the device id is the file
stem. Other column names and units are mapped at load time
(:func:`parse_columns`, ``units=``); a unit written in a header
(``Gyroscope X (deg/s)``) is read from it (:mod:`.headers`), and the numbers of
a signal whose unit nobody stated are checked for plausibility in SI
(:mod:`.plausible`: refused, or warned about, naming the option that passes;
one :class:`UnitNote` line each in the :class:`LoadReport`). PX4 ULog, ROS bags and ArduPilot
DataFlash logs are read by :mod:`diffgyro.logs` into the same schema and then
checked like any table.

Bad input raises :class:`~diffgyro.errors.DataError` naming file, device,
column and row. **Row convention:** ``row N`` is the N-th data row of the
file counted from 1 after the header line (blank lines are not rows); Parquet
and NPZ rows are numbered the same way (row 1 = first record). Rows are never
reordered: a device's samples keep their file order, devices keep the order of
their first appearance. Nothing is dropped unless ``drop_invalid=True``, and
then only rows with invalid cells, with the count reported in a
:class:`LoadReport`.

**Invalid cells** are empty, NaN or infinite values, values that overflow in
the unit conversion, and values no instrument gives (:data:`LIMITS`, in SI
units after conversion): a rate (``gx..gz``, ``rx..rz``) or a specific force
(``ax..az``) beyond ±10⁸, a temperature (``temp``, ``temp_ext``) below
absolute zero (−273.15 °C) or above 500 °C. The rate and force limits lie far
above physics (the fastest rotors turn at ~10⁴ rad/s, shock accelerometers
read ~10⁶ m/s²) and above a 24-bit converter's full scale (8.4·10⁶), so raw
ADC counts, which the multi- and six-position recipes calibrate, still load.
Each is refused like NaN, naming file, device, column and row.

Writing (:func:`save`) uses the shortest round-trip decimal form for float64,
so loading a saved file gives bitwise identical values.
"""


from __future__ import annotations

from ._cells import LIMITS, cell_problem, check_cells
from ._columns import parse_columns
from ._load import load, load_batch
from ._plausible import check_plausible
from ._reports import Dropped, LoadReport, UnitNote, check_min_samples
from ._save import save
from ._units import UNITS, resolve_units

__all__ = ["load", "load_batch", "save", "LoadReport", "UNITS", "Dropped", "LIMITS", "UnitNote",
           "cell_problem", "check_cells", "check_plausible", "check_min_samples", "parse_columns",
           "resolve_units"]

