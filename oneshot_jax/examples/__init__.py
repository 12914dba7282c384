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
"""

from . import cascaded_tanks as cascaded_tanks
from . import chain as chain
from . import emps as emps
from . import satellite as satellite
