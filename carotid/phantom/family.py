"""The phantom family: the class of inputs the segmentation is meant for, as ranges to draw from."""

from __future__ import annotations

import numpy as np

from carotid.phantom.ct import MAGNITUDE, MODALITIES, TOF_ARTERIAL, TOF_TISSUE, rescale

# The ranges of :func:`sample_family` (units in the keys' names or in its docstring).
FAMILY_RANGES = {
    "stenosis": (0.3, 0.9),                 # ICA area reduction
    "noise_ct_hu": (10.0, 40.0),
    "blur_sigma_mm": (0.4, 0.8),
    "spacing_in_plane_mm": (0.4, 0.5),
    "spacing_z_mm": (0.4, 1.0),             # at least the in-plane spacing
    "vein_gap_mm": (0.3, 2.0),
    "venous_fraction": (0.4, 0.9),
    "calcium_hu": (300.0, 1500.0),          # at least 50 HU above the arterial level
    "no_calcium_probability": 0.15,
    "plaque_size": (0.6, 1.5),
    "plaque_angle_deg": (0.0, 360.0),
    "plaque_offset_mm": (-2.5, 2.5),
    "arterial_hu": (250.0, 600.0),
    "arterial_mr": (1200.0, 2500.0),
    "bolus_fade": (0.0, 0.3),
    "ica_shape": {"smooth": 0.6, "kink": 0.2, "loop": 0.2},
    "mr_probability": 0.2,
    "bias": (0.15, 0.4),
}
MR_TISSUE_NOMINAL = 275.0  # the middle of the MR muscle range, for the noise scaling


def sample_family(seed: int, modality: str | None = None) -> dict:
    """Draw the keyword arguments of one phantom of the family.

    The family is the class of inputs the segmentation is meant for.  Every value is drawn
    uniformly from its range (``FAMILY_RANGES``), always in the same order, so that forcing the
    modality does not change the anatomy or the other draws:

    * ``stenosis``: ICA area reduction 0.3-0.9 (NASCET about 0-0.65 with the bulb);
    * ``noise``: CT 10-40 HU; MR the same contrast-to-noise ratio as a CT draw, i.e. a CT noise
      and arterial level are drawn and the MR sigma is noise_ct / (arterial_ct - 40 HU) x
      (lumen_mr - 275) in MR units (Rician);
    * ``blur_sigma_mm``: 0.4-0.8 mm (standard deviation in plane, 1.25 x along z);
    * ``spacing``: in plane 0.4-0.5 mm, slices from the in-plane value to 1.0 mm (from isotropic
      0.4 mm to 0.5 x 0.5 x 1.0 mm);
    * ``vein_gap_mm``: 0.3-2 mm, the smallest gap between the jugular vein and the arterial lumen;
    * ``venous_fraction``: 0.4-0.9 of the proximal arterial enhancement above tissue;
    * plaque: none in 15 % of the cases (``plaque_size`` 0); otherwise ``plaque_size`` 0.6-1.5,
      ``plaque_angle_deg`` 0-360, ``plaque_offset_mm`` -2.5 to 2.5 from the throat and, in CT,
      ``calcium_hu`` from max(300, arterial + 50) to 1500 HU (barely above the lumen to blooming);
      in MR calcium is a signal void;
    * ``arterial_hu``: CT 250-600 HU; MR 1200-2500 units (proximal lumen level);
    * ``bolus_fade``: 0-0.3 of the arterial enhancement lost from the proximal CCA to the distal
      ICA;
    * ``ica_shape``: smooth 60 %, kink 20 %, loop 20 %;
    * ``modality``: "mr" in 20 % of the cases when ``modality`` is None, else as given; MR adds a
      ``bias`` field of amplitude 0.15-0.4.  "tof" (time-of-flight MRA) is never drawn, only forced:
      the MR draws are placed in its ranges (``arterial_hu`` 400-1000 units, muscle at 10-20 % of
      it; the noise at the same contrast-to-noise ratio as the CT draw, against the muscle).

    Parameters
    ----------
    seed : int
        Seed of the draw (>= 0); it is also the phantom's own ``seed``.
    modality : {"ct", "mr", "tof"} or None
        Force the modality; None draws it (CT or contrast-enhanced MR).

    Returns
    -------
    dict
        JSON-ready keyword arguments of :func:`carotid.phantom.make_phantom` (no field of view:
        the default 44 x 44 x 75 mm); ``make_phantom(**sample_family(seed))`` builds the phantom.
    """
    from carotid.errors import CarotidError

    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise CarotidError(f"seed {seed!r} must be a non-negative integer")
    if modality is not None and modality not in MODALITIES:
        raise CarotidError(f"modality {modality!r} must be one of {', '.join(MODALITIES)} or None")
    R = FAMILY_RANGES
    rng = np.random.default_rng([int(seed), 1000])
    u = lambda key: float(rng.uniform(*R[key]))  # noqa: E731
    stenosis = u("stenosis")
    noise_ct = u("noise_ct_hu")
    blur = u("blur_sigma_mm")
    in_plane = u("spacing_in_plane_mm")
    slice_z = float(rng.uniform(in_plane, R["spacing_z_mm"][1]))
    gap = u("vein_gap_mm")
    venous = u("venous_fraction")
    no_calcium = rng.uniform() < R["no_calcium_probability"]
    size, angle, offset = u("plaque_size"), u("plaque_angle_deg"), u("plaque_offset_mm")
    arterial_ct = u("arterial_hu")
    arterial_mr = u("arterial_mr")
    calcium_unit = rng.uniform()
    fade = u("bolus_fade")
    shapes = list(R["ica_shape"])
    shape = shapes[int(rng.choice(len(shapes), p=list(R["ica_shape"].values())))]
    drawn_mr = rng.uniform() < R["mr_probability"]
    bias = u("bias")
    mr = drawn_mr if modality is None else modality in MAGNITUDE
    tof = modality == "tof"

    kwargs = {
        "stenosis": round(stenosis, 4), "seed": int(seed),
        "spacing": [round(in_plane, 3), round(in_plane, 3), round(slice_z, 3)],
        "blur_sigma_mm": round(blur, 3), "vein_gap_mm": round(gap, 3), "venous_fraction": round(venous, 3),
        "plaque_size": 0.0 if no_calcium else round(size, 3), "bolus_fade": round(fade, 3), "ica_shape": shape,
        "modality": modality or ("mr" if mr else "ct"),
    }
    if not no_calcium:
        kwargs["plaque_angle_deg"] = round(angle, 1)
        kwargs["plaque_offset_mm"] = round(offset, 2)
    if mr:
        arterial, tissue = arterial_mr, MR_TISSUE_NOMINAL
        if tof:
            arterial = rescale(arterial_mr, R["arterial_mr"], TOF_ARTERIAL)
            tissue = arterial * float(np.mean(TOF_TISSUE))
        kwargs["arterial_hu"] = round(arterial, 1)
        kwargs["noise"] = round(noise_ct / (arterial_ct - 40.0) * (arterial - tissue), 1)
        kwargs["bias"] = round(bias, 3)
    else:
        kwargs["arterial_hu"] = round(arterial_ct, 1)
        kwargs["noise"] = round(noise_ct, 1)
        if not no_calcium:
            low = max(R["calcium_hu"][0], arterial_ct + 50.0)
            kwargs["calcium_hu"] = round(low + calcium_unit * (R["calcium_hu"][1] - low), 1)
    return kwargs
