"""An apple's mass from its diameter, per cultivar (issue 59): its density times the volume of a sphere of its
diameter. One relation for the simulator's truth and the ground's kilograms.

The density is that of whole Fuji apples weighed and their volume measured, six commercial sizes (30-89 fruit per
15 kg): specific volume 1.13-1.18 mL/g, 1.16 in the mean, that is 0.86 g/mL (Korean Journal of Food Preservation
21(5):618, Table 1, "Physicochemical characteristics of apple by cultivar and size"; 'Royal Fuji' the same within
0.01). Other cultivars take it until measured: give theirs in CULTIVAR_DENSITY_KG_M3.
"""

from __future__ import annotations

import numpy as np

#: Whole-fruit density (kg/m^3) by cultivar (lower case); DEFAULT_DENSITY_KG_M3 for any other.
CULTIVAR_DENSITY_KG_M3 = {"fuji": 860.0, "royal fuji": 870.0}
DEFAULT_DENSITY_KG_M3 = 860.0


def apple_mass_kg(diameter_m, cultivar: str | None = None) -> np.ndarray:
    """The mass (kg) of apples of these diameters (m)."""
    rho = CULTIVAR_DENSITY_KG_M3.get((cultivar or "").lower(), DEFAULT_DENSITY_KG_M3)
    return rho * np.pi / 6.0 * np.asarray(diameter_m, float) ** 3
