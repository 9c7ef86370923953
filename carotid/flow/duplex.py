"""Virtual duplex ultrasound: Doppler gates in the simulated flow, the SRU consensus grade, and an inflow
calibrated to measured CCA velocities.

Gates.  A Doppler gate reads the highest velocity in its sample volume.  Here a gate is a sphere on the vessel
axis of radius ``GATE_RADIUS_FRACTION`` (0.5) of the local lumen radius (the maximal inscribed sphere of the
centerline), capped at ``GATE_RADIUS_CAP_MM`` (1 mm; a clinical sample volume is 1.5-2 mm long), sampled by 43
points (:func:`carotid.flow.probes.sphere_offsets`); its reading at a time is the largest speed ``|u|`` among
them, taken from the solver's state at every probe sample (:class:`carotid.flow.probes.ProbeRecorder`).  The
gates sit

* in the ICA at its narrowest section (``geometry.json`` ``stenoses``, branch ICA, ``location_mm``): the
  stenosis velocity;
* in the CCA ``CCA_GATE_MM`` (20 mm) proximal to the bifurcation point along the CCA's arc length, the usual
  CCA reference site, or as far from it as the CCA inside the mesh allows (one local diameter from the inlet
  cap); the distance used is recorded.

Over the last whole cycle, PSV is the largest reading and EDV the reading at end diastole: the smallest reading
over the ``END_DIASTOLE_WINDOW`` (30 %) of the cycle before the systolic peak, i.e. the foot of the systolic
upstroke, where the SRU consensus reads it (just before the next upstroke).  The cycle's last sample is not used:
a waveform may start anywhere in the cycle (the built-in one starts in late diastole, 55 ms before the foot).  The
window wraps round the cycle's start; in a run's first cycle, which starts from rest, its first ``START_UP``
(10 %) is start-up and left out, so the late diastole at the cycle's end stands for the foot (for the built-in
waveform this reads the velocity 55 ms before the foot: a few % above it; run two cycles or more to avoid it).

Pressure across the stenosis: proximal at the CCA gate's centre (where a catheter measuring the translesional
gradient sits), distal on the ICA axis ``DISTAL_DIAMETERS`` (3) distal ICA diameters beyond the far end of the
lesion (its full width at half depth), or one diameter before the ICA leaves the mesh if that comes first.  The
drop is given time-averaged over the cycle and at peak systole (the inflow's peak); the ratio distal/proximal
(as Pd/Pa) only when lumped outlets make the pressures absolute, since with a prescribed split they are relative
to the mean outlet pressure.

Grade (Grant et al., Carotid artery stenosis: gray-scale and Doppler US diagnosis - Society of Radiologists in
Ultrasound consensus conference, Radiology 2003;229:340-346).  The primary parameter is the ICA PSV: < 125 cm/s
normal (no plaque) or < 50 %, 125-230 cm/s 50-69 %, > 230 cm/s >= 70 %; the additional parameters are the ICA/CCA
PSV ratio (< 2, 2-4, > 4) and the ICA EDV (< 40, 40-100, > 100 cm/s).  Near occlusion (velocities variable) is
taken from the geometry (:func:`carotid.report.checks.stenosis_category`), total occlusion cannot arise in a
simulation.  Plaque (B-mode) is taken from the geometry too: a diameter reduction of at least ``PLAQUE_ECST``
(10 %) at the narrowest ICA section against its local reference (ECST).  Each parameter's category is given, with
whether they agree.

Calibrated inflow.  Given a measured CCA PSV and EDV, the inflow waveform ``q(t)`` is replaced by
``a q(t) + b`` so that the centreline velocity of the generalised Womersley profile on the actual inlet face
(:func:`carotid.flow.womersley.inlet_profile`) is the PSV at its systolic peak and the EDV at its end diastole
(same definition as the gates).  The profile is linear in the flow: the centreline velocity of ``a q + b`` is
``a u_c(t) + b s_0``, ``u_c`` that of ``q`` and ``s_0`` the steady (Poiseuille-like) centreline velocity per unit
flow, and ``a > 0`` keeps the times of the peak and of end diastole, so two linear conditions give ``a`` and
``b`` exactly.  The Womersley profile is blunter than Poiseuille's in systole: assuming ``u_c = 2 q / A`` would
miss the targets by several % at the carotid's Womersley number (~4).
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from carotid.errors import CarotidError, CarotidWarning
from carotid.flow.mesh import MM
from carotid.flow.probes import PointLocator, ProbeSet, ProbeSpec

GATE_RADIUS_FRACTION = 0.5
"""Gate radius as a fraction of the local lumen radius."""
GATE_RADIUS_CAP_MM = 1.0
"""Largest gate radius, mm."""
CCA_GATE_MM = 20.0
"""Arc length of the CCA gate proximal to the bifurcation point, mm."""
END_DIASTOLE_WINDOW = 0.3
"""End diastole: the minimum over this fraction of the cycle before the systolic peak."""
DISTAL_DIAMETERS = 3.0
"""The distal pressure point lies this many distal ICA diameters beyond the lesion's far end."""
END_MARGIN_DIAMETERS = 1.0
"""Gates and pressure points stay this many local diameters inside the part of a centerline within the mesh."""
PLAQUE_ECST = 0.1
"""Diameter reduction (ECST) of the narrowest ICA section from which it counts as plaque (SRU normal vs < 50 %)."""
CENTRELINE_SPACING = 1.0
"""Centreline probes: one every this many local diameters along each branch."""
MATCHING_FRACTION = 0.7
"""Centerlines with fewer of their points inside the mesh are not the mesh's (a case's own: 0.85-0.95, the rest
beyond the caps; another case's tube over a bifurcation mesh: 0.43)."""

SRU_PSV_CM_S = (125.0, 230.0)
"""SRU consensus ICA PSV bounds, cm/s: below the first < 50 %, up to the second 50-69 %, above it >= 70 %."""
SRU_RATIO = (2.0, 4.0)
"""SRU consensus ICA/CCA PSV ratio bounds."""
SRU_EDV_CM_S = (40.0, 100.0)
"""SRU consensus ICA EDV bounds, cm/s."""

START_UP = 0.1
"""In a run's first cycle (from rest), the samples of this fraction of the cycle are start-up, not end diastole."""

DOPPLER_PSV_CM_S = (10.0, 250.0)
"""Plausible CCA peak systolic velocities for ``--doppler-cca``, cm/s."""


def peak_and_end_diastole(times: np.ndarray, values: np.ndarray, period: float,
                          settled: float = -np.inf) -> tuple[int, int]:
    """Indices of the systolic peak and of end diastole in one cycle of samples.

    Parameters
    ----------
    times : ndarray, shape (T,)
        Sample times spanning (at most) one cycle, s.
    values : ndarray, shape (T,)
        Velocity (or speed) samples, m/s.
    period : float
        Cycle length, s.
    settled : float
        Samples before this time (s) are not end diastole (the start-up of a run from rest), unless the window
        holds no other (a run shorter than that).

    Returns
    -------
    (int, int)
        The largest sample, and the smallest sample within ``END_DIASTOLE_WINDOW * period`` before it (the times
        taken modulo the period, so the window wraps round the cycle's start), at or after ``settled``.
    """
    peak = int(np.argmax(values))
    before = np.mod(times[peak] - times, period)
    window = before <= END_DIASTOLE_WINDOW * period
    window = np.flatnonzero(window & (times >= settled) if np.any(window & (times >= settled)) else window)
    return peak, int(window[np.argmin(values[window])])


def sru_category(value: float, bounds: tuple[float, float]) -> str:
    """``"<50 %"`` below ``bounds[0]``, ``"50-69 %"`` from it up to ``bounds[1]`` inclusive, ``">=70 %"`` above."""
    if value < bounds[0]:
        return "<50 %"
    return "50-69 %" if value <= bounds[1] else ">=70 %"


def sru_grade(psv_cm_s: float, edv_cm_s: float, ratio: float, plaque: bool, near_occlusion: bool) -> dict:
    """The SRU consensus grade of an ICA stenosis (Grant et al. 2003).

    Parameters
    ----------
    psv_cm_s, edv_cm_s : float
        ICA peak systolic and end-diastolic velocity, cm/s.
    ratio : float
        ICA PSV / CCA PSV.
    plaque : bool
        Whether plaque is seen (here: from the geometry).
    near_occlusion : bool
        Whether the lumen is nearly occluded (the velocities then do not grade it).

    Returns
    -------
    dict
        ``grade`` (``"normal"``, ``"<50 %"``, ``"50-69 %"``, ``">=70 %"`` or ``"near occlusion"``) from the PSV,
        the primary parameter; ``by_psv``, ``by_ratio``, ``by_edv``, each parameter's category; ``concordant``,
        whether the three agree (normal counting as < 50 %).
    """
    by = {"by_psv": sru_category(psv_cm_s, SRU_PSV_CM_S), "by_ratio": sru_category(ratio, SRU_RATIO),
          "by_edv": sru_category(edv_cm_s, SRU_EDV_CM_S)}
    grade = ("near occlusion" if near_occlusion else
             "normal" if by["by_psv"] == "<50 %" and not plaque else by["by_psv"])
    return {"grade": grade, **by, "concordant": len(set(by.values())) == 1}


def _along(branch, s: np.ndarray, at) -> tuple[np.ndarray, float]:
    """Point (3,) mm and inscribed radius (mm) at arc length ``at`` (mm) of a branch with arc lengths ``s``."""
    point = np.array([np.interp(at, s, branch.points[:, d]) for d in range(3)])
    return point, float(np.interp(at, s, branch.radii))


def _inside_range(branch, s: np.ndarray, locator: PointLocator) -> tuple[float, float] | None:
    """Arc lengths (mm) of the first and last points of ``branch`` inside the mesh, each pulled in by
    ``END_MARGIN_DIAMETERS`` local diameters where the centerline leaves the mesh there (through a cap; not at the
    bifurcation); None when no point is inside or nothing is left."""
    inside = np.flatnonzero(locator.locate(branch.points * MM)[0] >= 0)
    if not inside.size:
        return None
    leaves = np.array([inside[0] > 0, inside[-1] < len(s) - 1])
    margin = 2.0 * END_MARGIN_DIAMETERS * branch.radii[inside[[0, -1]]] * leaves
    lo, hi = s[inside[0]] + margin[0], s[inside[-1]] - margin[1]
    return (float(lo), float(hi)) if lo <= hi else None


def gate_radius_mm(local_radius_mm: float) -> float:
    """Radius of a gate's sample volume for a lumen of inscribed radius ``local_radius_mm``, mm."""
    return min(GATE_RADIUS_FRACTION * local_radius_mm, GATE_RADIUS_CAP_MM)


def duplex_probes(cl, geometry: dict, locator: PointLocator) -> tuple[list[ProbeSpec], dict]:
    """The Doppler gates and pressure points of a case.

    Parameters
    ----------
    cl : carotid.centerline.model.Centerlines
        Centerlines, mm.
    geometry : dict
        :func:`carotid.centerline.features.geometry_features` of ``cl`` (``stenoses``: the ICA's grading).
    locator : PointLocator
        Of the flow mesh (m): keeps the gates inside the part of each centerline within the mesh.

    Returns
    -------
    specs : list of ProbeSpec
        ``ICA_gate`` and ``CCA_gate`` (spheres), ``ICA_distal`` (a point; the proximal pressure is the CCA
        gate's centre); empty when the case has no CCA and ICA or no ICA grading.
    meta : dict
        The choices made (arc lengths, the lesion), or ``reason`` when there are no gates.
    """
    from carotid.centerline.axes import arclength

    names = [b.name for b in cl.branches]
    grade = next((g for g in geometry.get("stenoses") or [] if g["branch"] == "ICA"), None)
    if not {"CCA", "ICA"} <= set(names) or grade is None:
        return [], {"reason": "no CCA and graded ICA in the centerlines"}
    cca, ica = cl.branch("CCA"), cl.branch("ICA")
    s_cca, s_ica = arclength(cca.points), arclength(ica.points)
    cca_range, ica_range = _inside_range(cca, s_cca, locator), _inside_range(ica, s_ica, locator)
    if cca_range is None or ica_range is None:
        return [], {"reason": "the CCA or the ICA centerline does not run inside the mesh"}
    at_ica = float(s_ica[np.argmin(np.linalg.norm(ica.points - np.asarray(grade["location_mm"]), axis=1))])
    if not ica_range[0] <= at_ica <= ica_range[1]:
        return [], {"reason": f"the narrowest ICA section ({at_ica:.1f} mm from the bifurcation) is not a diameter "
                              "inside the mesh"}
    bifurcation = cl.bifurcation if np.all(np.isfinite(cl.bifurcation)) else cca.points[-1]
    s_bif = float(s_cca[np.argmin(np.linalg.norm(cca.points - bifurcation, axis=1))])
    at_cca = float(np.clip(s_bif - CCA_GATE_MM, *cca_range))
    far = float(grade["extent_from_bifurcation_mm"][1])
    at_distal = float(min(far + DISTAL_DIAMETERS * grade["distal_diameter_mm"], ica_range[1]))
    (p_ica, r_ica), (p_cca, r_cca) = _along(ica, s_ica, at_ica), _along(cca, s_cca, at_cca)
    p_distal, _ = _along(ica, s_ica, at_distal)
    specs = [ProbeSpec("ICA_gate", p_ica, gate_radius_mm(r_ica), "gate",
                       {"branch": "ICA", "arclength_from_bifurcation_mm": at_ica, "local_radius_mm": r_ica}),
             ProbeSpec("CCA_gate", p_cca, gate_radius_mm(r_cca), "gate",
                       {"branch": "CCA", "arclength_from_bifurcation_mm": s_bif - at_cca,
                        "local_radius_mm": r_cca}),
             ProbeSpec("ICA_distal", p_distal, 0.0, "pressure",
                       {"branch": "ICA", "arclength_from_bifurcation_mm": at_distal})]
    return specs, {"lesion_extent_mm": [float(v) for v in grade["extent_from_bifurcation_mm"]],
                   "ica_grade": grade}


def centreline_probes(cl, locator: PointLocator) -> list[ProbeSpec]:
    """Point probes along each branch's centerline, one every ``CENTRELINE_SPACING`` local diameters, inside the mesh.

    Named ``<branch>_<k>`` (k from 1, with the flow: from the inlet along the CCA, from the bifurcation along the
    others); ``info`` holds the arc length from the bifurcation point (mm).
    """
    from carotid.centerline.axes import arclength

    specs = []
    for branch in cl.branches:
        s = arclength(branch.points)
        count = np.r_[0.0, np.cumsum(np.diff(s) / (CENTRELINE_SPACING * (branch.radii[1:] + branch.radii[:-1])))]
        at = np.interp(np.arange(np.ceil(count[-1]) if count[-1] > 0 else 0), count, s)
        points = np.column_stack([np.interp(at, s, branch.points[:, d]) for d in range(3)])
        inside = locator.locate(points * MM)[0] >= 0
        from_bif = s[-1] - at if branch.name == "CCA" else at
        specs += [ProbeSpec(f"{branch.name}_{k + 1}", points[i], 0.0, "centreline",
                            {"branch": branch.name, "arclength_from_bifurcation_mm": float(from_bif[i])})
                  for k, i in enumerate(np.flatnonzero(inside))]
    return specs


def case_probes(case_dir, mesh, user=()) -> tuple[ProbeSet, dict]:
    """Every probe of a run: the user's points, then the Doppler gates and pressure point (:func:`duplex_probes`)
    and the centreline probes (:func:`centreline_probes`) when the case has centerlines.

    Parameters
    ----------
    case_dir : path
        Case folder (``centerlines.vtp``).
    mesh : carotid.flow.mesh.FlowMesh
    user : sequence of (name, (x, y, z))
        The user's probe points, mm LPS.

    Returns
    -------
    ProbeSet, dict
        The located probes (a user's point outside the fluid raises CarotidError), and the meta of
        :func:`duplex_probes` (``reason`` when there are no gates).  Centerlines with under
        ``MATCHING_FRACTION`` of their points inside the mesh are another's: no gates nor centreline probes.
        When the case has centerlines but gets no gates, a CarotidWarning gives the reason.
    """
    from carotid.centerline import geometry_features, read_centerlines

    locator = PointLocator(mesh.points, mesh.tets)
    specs = [ProbeSpec(str(name), np.asarray(xyz, dtype=float), 0.0, "user") for name, xyz in user]
    meta = {"reason": "no centerlines.vtp in the case folder"}
    path = Path(case_dir) / "centerlines.vtp"
    if path.exists():
        cl = read_centerlines(path)
        inside = np.mean(locator.locate(np.concatenate([b.points for b in cl.branches]) * MM)[0] >= 0)
        if inside < MATCHING_FRACTION:
            meta = {"reason": f"the centerlines do not match the mesh: {100 * inside:.0f} % of their points lie "
                              f"inside it, a case's own {100 * MATCHING_FRACTION:.0f} % or more (centerlines.vtp of "
                              "another case or an earlier segmentation? rerun `carotid centerlines`)"}
        else:
            gates, meta = duplex_probes(cl, geometry_features(cl), locator)
            specs += gates + centreline_probes(cl, locator)
        if "reason" in meta:
            warnings.warn(f"no virtual duplex: {meta['reason']}", CarotidWarning, stacklevel=2)
    return ProbeSet(mesh, specs, locator), meta


def duplex_summary(times: np.ndarray, values: dict, specs: dict, period: float, t_systole: float,
                   lumped: bool, meta: dict) -> dict:
    """The ``duplex`` section of summary.json from the gate and pressure series of the last cycle.

    Parameters
    ----------
    times : ndarray, shape (T,)
        Sample times of (at most) the last cycle, s.
    values : dict
        Probe name -> samples (T, 5) (:meth:`carotid.flow.probes.ProbeSet.sample`: u, v, w, speed m/s, p Pa) of
        ``ICA_gate``, ``CCA_gate`` and ``ICA_distal``.
    specs : dict
        Probe name -> :class:`carotid.flow.probes.ProbeSpec`.
    period : float
        Cycle length, s.
    t_systole : float
        Time of the inflow's systolic peak within the sampled cycle, s.
    lumped : bool
        Whether the pressures are absolute (lumped outlets).
    meta : dict
        Of :func:`duplex_probes`.

    Returns
    -------
    dict
        ``gates`` (per gate: position mm, radius mm, PSV and EDV in m/s and cm/s with their times), ``psv_ratio``,
        ``pressure`` (positions, drop mean and at peak systole in Pa and mmHg, ratio or None, reference), ``sru``
        (:func:`sru_grade`), ``nascet`` and its category, and the definitions used.
    """
    from carotid.flow.indices import trapezoid_weights
    from carotid.flow.outlets import MMHG
    from carotid.report.checks import stenosis_category

    gates = {}
    settled = START_UP * period if times[0] <= 0.0 else -np.inf  # a first cycle, from rest
    for name in ("ICA_gate", "CCA_gate"):
        speed = values[name][:, 3]
        peak, end = peak_and_end_diastole(times, speed, period, settled)
        spec = specs[name]
        gates[name.split("_")[0]] = {
            "position_mm": [float(v) for v in spec.centre_mm], "gate_radius_mm": spec.radius_mm, **spec.info,
            "psv_m_s": float(speed[peak]), "edv_m_s": float(speed[end]), "psv_cm_s": 100 * float(speed[peak]),
            "edv_cm_s": 100 * float(speed[end]), "psv_time_s": float(times[peak]), "edv_time_s": float(times[end])}
    ratio = gates["ICA"]["psv_m_s"] / gates["CCA"]["psv_m_s"]
    proximal, distal = values["CCA_gate"][:, 4], values["ICA_distal"][:, 4]
    weights = trapezoid_weights(times)
    weights = weights / weights.sum() if weights.sum() > 0 else np.full(len(times), 1.0 / len(times))
    sys = int(np.argmin(np.abs(times - t_systole)))
    drop_mean, drop_sys = float(weights @ (proximal - distal)), float(proximal[sys] - distal[sys])
    pressure = {
        "proximal": "the CCA gate's centre", "proximal_position_mm": gates["CCA"]["position_mm"],
        "distal": f"the ICA axis {DISTAL_DIAMETERS:g} distal ICA diameters beyond the lesion's far end (or one "
                  "diameter before the ICA leaves the mesh)",
        "distal_position_mm": [float(v) for v in specs["ICA_distal"].centre_mm],
        "distal_arclength_from_bifurcation_mm": specs["ICA_distal"].info["arclength_from_bifurcation_mm"],
        "reference": "absolute (lumped outlets)" if lumped else
                     "relative (prescribed split): the drop is meaningful, the ratio is not",
        "drop_mean_pa": drop_mean, "drop_mean_mmhg": drop_mean / MMHG,
        "drop_peak_systole_pa": drop_sys, "drop_peak_systole_mmhg": drop_sys / MMHG,
        "peak_systole_time_s": float(times[sys]),
        "ratio_mean": float((weights @ distal) / (weights @ proximal)) if lumped else None,
        "ratio_peak_systole": float(distal[sys] / proximal[sys]) if lumped else None}
    grade = meta["ica_grade"]
    category = stenosis_category(grade["nascet"], grade["min_diameter_mm"], grade["distal_diameter_mm"])
    sru = sru_grade(gates["ICA"]["psv_cm_s"], gates["ICA"]["edv_cm_s"], ratio, grade["ecst"] >= PLAQUE_ECST,
                    category == "near-occlusion")
    return {
        "gates": gates, "psv_ratio": ratio, "pressure": pressure, "sru": sru,
        "nascet": grade["nascet"], "nascet_category": category, "ecst": grade["ecst"],
        "samples": len(times), "cycle_from_s": float(times[0]), "cycle_to_s": float(times[-1]),
        "first_cycle": bool(times[0] <= 0.0),
        "definitions": {
            "gate": f"sphere on the axis, radius {GATE_RADIUS_FRACTION:g} x the local inscribed radius, at most "
                    f"{GATE_RADIUS_CAP_MM:g} mm, 43 sample points; reading = the largest |u| among them",
            "psv": "largest gate reading over the last cycle",
            "edv": f"smallest gate reading over the {100 * END_DIASTOLE_WINDOW:g} % of the cycle before the systolic "
                   "peak (the foot of the upstroke, the SRU convention); in a first cycle from rest, not in its first "
                   f"{100 * START_UP:g} % (start-up), so that the cycle's end stands for the end diastole before it",
            "cca_gate": f"{CCA_GATE_MM:g} mm proximal to the bifurcation point along the CCA, or as far as the CCA "
                        "inside the mesh allows (arclength_from_bifurcation_mm)",
            "plaque": f"ECST of the narrowest ICA section >= {PLAQUE_ECST:g}",
            "sru": "Grant et al., Radiology 2003;229:340-346: PSV < 125 cm/s < 50 % (normal without plaque), "
                   "125-230 cm/s 50-69 %, > 230 cm/s >= 70 %; ratio < 2, 2-4, > 4; EDV < 40, 40-100, > 100 cm/s; "
                   "the grade follows the PSV"}}


def inlet_centreline(profile, times: np.ndarray) -> tuple[np.ndarray, float]:
    """Centreline velocity of an inlet profile over time, and its steady part per unit flow.

    The centreline is the inlet face node where the steady (k = 0) mode is largest: the centre of a circular face,
    the deepest point of the profile on any face.

    Parameters
    ----------
    profile : carotid.flow.womersley.InletProfile
    times : ndarray, shape (T,)
        s.

    Returns
    -------
    u : ndarray, shape (T,)
        Axial velocity at that node, m/s.
    steady : float
        Its steady velocity per unit mean flow, (m/s) / (m^3/s).
    """
    centre = int(np.argmax(profile.modes[0].real))
    return profile.velocity(times)[:, centre], float(profile.modes[0, centre].real / profile.flow_harmonics[0].real)


def calibrate_inflow(waveform, points, triangles, normal, nu: float, n_harmonics: int, psv_m_s: float,
                     edv_m_s: float, samples: int = 2048):
    """The inflow ``a q(t) + b`` whose Womersley centreline velocity on the inlet face has the measured PSV and EDV.

    Parameters
    ----------
    waveform : carotid.flow.waveform.Waveform
        Shape of the inflow q(t).
    points, triangles, normal
        The inlet face (m), as :func:`carotid.flow.womersley.inlet_profile` takes them.
    nu : float
        Kinematic viscosity, m^2/s.
    n_harmonics : int
    psv_m_s, edv_m_s : float
        Targets: CCA peak systolic and end-diastolic centreline velocity, m/s.
    samples : int
        Time samples per cycle locating the peak and end diastole.

    Returns
    -------
    waveform : Waveform
        The calibrated inflow.
    profile : InletProfile
        Its inlet profile.
    record : dict
        ``a``, ``b_ml_s``, the resulting mean, peak and minimum flow (mL/s), the targets and the centreline PSV
        and EDV achieved (cm/s), their times (s), and those of the uncalibrated waveform.

    Raises
    ------
    CarotidError
        PSV <= EDV, EDV < 0, values outside ``DOPPLER_PSV_CM_S``, a steady waveform, or a calibrated inflow
        whose mean would not enter the inlet.
    """
    from carotid.flow.waveform import ML
    from carotid.flow.womersley import inlet_profile

    check_doppler(100 * psv_m_s, 100 * edv_m_s)
    profile = inlet_profile(points, triangles, normal, waveform, nu, n_harmonics)
    times = np.arange(samples) * (waveform.period_s / samples)
    u, steady = inlet_centreline(profile, times)
    peak, end = peak_and_end_diastole(times, u, waveform.period_s)
    if not u[peak] - u[end] > 1e-9 * max(abs(u[peak]), 1e-30):
        raise CarotidError("--doppler-cca needs a pulsatile inflow waveform (a constant --flow has no systole)")
    a = (psv_m_s - edv_m_s) / (u[peak] - u[end])
    b = (psv_m_s - a * u[peak]) / steady
    new = waveform.affine(a, b)
    if not new.mean_m3s > 0:
        raise CarotidError(f"--doppler-cca {100 * psv_m_s:g} {100 * edv_m_s:g}: the calibrated inflow's mean would "
                           f"be {new.mean_m3s / ML:.3g} mL/s, not into the CCA")
    calibrated = inlet_profile(points, triangles, normal, new, nu, n_harmonics)
    achieved, _ = inlet_centreline(calibrated, times)
    flow = new.flow(times)
    return new, calibrated, {
        "a": float(a), "b_ml_s": float(b / ML), "mean_flow_ml_s": new.mean_m3s / ML,
        "peak_flow_ml_s": float(flow.max() / ML), "min_flow_ml_s": float(flow.min() / ML),
        "target_psv_cm_s": 100 * psv_m_s, "target_edv_cm_s": 100 * edv_m_s,
        "inlet_psv_cm_s": 100 * float(achieved[peak]), "inlet_edv_cm_s": 100 * float(achieved[end]),
        "psv_time_s": float(times[peak]), "edv_time_s": float(times[end]),
        "uncalibrated_psv_cm_s": 100 * float(u[peak]), "uncalibrated_edv_cm_s": 100 * float(u[end]),
        "uncalibrated_mean_flow_ml_s": waveform.mean_m3s / ML,
        "method": "q -> a q + b so that the Womersley centreline velocity of the inlet face (its node of largest "
                  "steady velocity) is the PSV at its systolic peak and the EDV at its end diastole"}


def check_doppler(psv_cm_s: float, edv_cm_s: float) -> None:
    """Raise CarotidError unless ``DOPPLER_PSV_CM_S[0] <= PSV <= DOPPLER_PSV_CM_S[1]`` and ``0 <= EDV < PSV`` (cm/s)."""
    lo, hi = DOPPLER_PSV_CM_S
    if not (np.isfinite(psv_cm_s) and np.isfinite(edv_cm_s)):
        raise CarotidError(f"--doppler-cca takes two finite velocities in cm/s (got {psv_cm_s} {edv_cm_s})")
    if not lo <= psv_cm_s <= hi:
        raise CarotidError(f"--doppler-cca: a CCA peak systolic velocity of {psv_cm_s:g} cm/s is implausible "
                           f"(expected {lo:g}-{hi:g} cm/s)")
    if edv_cm_s < 0 or edv_cm_s >= psv_cm_s:
        raise CarotidError(f"--doppler-cca: the end-diastolic velocity ({edv_cm_s:g} cm/s) must be at least 0 and "
                           f"below the peak systolic velocity ({psv_cm_s:g} cm/s)")
