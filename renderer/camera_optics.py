"""The front cameras' assumed optics, where a sequence does not say (OSDaR23 publishes
neither): the exposure, which sets the object's motion blur, and the effective aperture
diameter, which sets its defocus at its distance (a lens focused at infinity). The
composite's defaults and ``RenderSpec``'s; a module of its own so that the spec reads
them without importing the renderer."""

EXPOSURE_S = 0.005
APERTURE_M = 0.004
