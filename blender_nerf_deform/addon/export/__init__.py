"""Export: the edited NeRF leaving the NeRF Deform engine, as an OpenVDB volume Cycles and EEVEE render."""
