"""Blood flow: the CBS solver, inlet waveforms and profiles, wall shear stress and its indices."""
