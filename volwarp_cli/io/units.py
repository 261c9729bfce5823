"""Length units as the formats spell them, in millimetres (volwarp's world unit).

The tables of every reader that meets a unit: the OME schema's ``UnitsLength``
symbols (OME-TIFF), ImageJ's words (TIFF stacks), what NRRD headers carry in
``space units`` and ``units`` (teem leaves them free text: ``mm``, ``microns``,
``cm``, ...), and the NGFF axes' UDUNITS names (OME-Zarr, :data:`NGFF_UNIT_TO_MM`).
"""

from __future__ import annotations

#: The OME schema's UnitsLength symbols (and the common spellings of micrometre and
#: ångström) in millimetres. ``pixel`` and ``reference frame`` are not lengths.
OME_LENGTH_TO_MM = {
    "Ym": 1e27, "Zm": 1e24, "Em": 1e21, "Pm": 1e18, "Tm": 1e15, "Gm": 1e12, "Mm": 1e9,
    "km": 1e6, "hm": 1e5, "dam": 1e4, "m": 1e3, "dm": 1e2, "cm": 10.0, "mm": 1.0,
    "\u00b5m": 1e-3, "\u03bcm": 1e-3, "um": 1e-3, "micron": 1e-3,
    "nm": 1e-6, "pm": 1e-9, "fm": 1e-12, "am": 1e-15, "zm": 1e-18, "ym": 1e-21,
    "\u00c5": 1e-7, "\u212b": 1e-7,
    "thou": 0.0254, "li": 25.4 / 12, "in": 25.4, "ft": 304.8, "yd": 914.4,
    "mi": 1609344.0, "ua": 1.495978707e14, "ly": 9.4607304725808e18,
    "pc": 3.0856775814913673e19, "pt": 25.4 / 72,
}

#: NGFF axis units (UDUNITS-2 names, and the common short forms) in millimetres: what
#: the OME-Zarr reader takes (another unit is refused there, naming these)
NGFF_UNIT_TO_MM = {
    "millimeter": 1.0, "mm": 1.0, "micrometer": 1e-3, "micron": 1e-3, "um": 1e-3,
    "\u00b5m": 1e-3, "nanometer": 1e-6, "nm": 1e-6, "picometer": 1e-9, "angstrom": 1e-7,
    "centimeter": 10.0, "cm": 10.0, "decimeter": 100.0, "meter": 1000.0, "m": 1000.0,
    "kilometer": 1e6, "inch": 25.4, "foot": 304.8, "yard": 914.4,
}

#: words for lengths (ImageJ's, Fiji writes "micron"; NRRD files' "microns", "millimeters")
_WORDS_MM = {"micron": 1e-3, "microns": 1e-3, "micrometer": 1e-3, "micrometre": 1e-3,
             "micrometers": 1e-3, "micrometres": 1e-3, "nanometer": 1e-6, "nanometers": 1e-6,
             "millimeter": 1.0, "millimetre": 1.0, "millimeters": 1.0, "millimetres": 1.0,
             "centimeter": 10.0, "centimetre": 10.0, "centimeters": 10.0, "centimetres": 10.0,
             "meter": 1e3, "metre": 1e3, "meters": 1e3, "metres": 1e3,
             "inch": 25.4, "inches": 25.4}


def length_unit_mm(unit: str) -> float | None:
    """A length unit's size in millimetres; None for no length (``pixel``) or an unknown word."""
    u = unit.strip().replace("\\u00B5", "\u00b5").replace("\\u00b5", "\u00b5")
    return OME_LENGTH_TO_MM.get(u, _WORDS_MM.get(u.lower()))
