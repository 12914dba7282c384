"""The example systems of the paper and the case studies, each defined once.

Each module holds one system's right-hand side (or step), its `Model` builder, its
physical constants and its data preparation; the experiments (`experiments/`), the
benchmarks (`benchmarks/`) and the quick start import them from here.

- `satellite`: the rigid-body satellite of Section 4 of the paper (Euler's equations,
  diagonal inertia), with the numpy data generator of the case study.
- `emps`: the EMPS benchmark (Electro-Mechanical Positioning System): the friction model,
  the open-loop and closed-loop (PD controller in the loop) models, windowing and
  velocity estimation of the records, and the benchmark's relative error.
- `cascaded_tanks`: the cascaded-tanks benchmark: Torricelli models without and with
  overflow.
- `chain`: a chain of masses with a spring and a damper per link (many parameters, a
  known initial state), with a numpy data generator.
- `cstr`: a continuous stirred-tank reactor with an exothermic reaction (concentration
  and temperature, the coolant temperature as input), time-stamped at irregular times,
  the concentration measured only as 8-hour averages; the data generator of the
  non-uniform observations guide and `benchmarks/cstr_coverage.py`.
"""

from . import cascaded_tanks as cascaded_tanks
from . import chain as chain
from . import cstr as cstr
from . import emps as emps
from . import satellite as satellite
