"""The simulated sensor of the examples: the one the demonstrations ship, run from here.

``python -S -I sim_sensor.py --output CHANNEL --name NAME [--rate HZ]`` sends ``<name> <seq>``
datagrams to CHANNEL (see ``temoto/demos/data/sim_sensor.py``, which this runs: one program,
two places that name it).
"""

import os
import runpy

if __name__ == "__main__":
    here = os.path.dirname(os.path.abspath(__file__))
    program = os.path.join(here, "..", "..", "temoto", "demos", "data", "sim_sensor.py")
    runpy.run_path(program, run_name="__main__")
