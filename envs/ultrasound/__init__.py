"""A B-mode-like ultrasound image of the slice of the deformed FE breast under the probe.

The image plane is the probe frame's z = 0 plane (``tissue`` module docstring): columns run
along x (lateral, from -aperture/2 to +aperture/2), rows along +y (depth, row 0 at the face).
It agrees with :func:`envs.observations.lesion_in_image`, which reports a lesion's centroid
in the same (lateral, depth) coordinates.

Per frame (:meth:`BModeImager.image`):

1. **Where each pixel is in the tissue.** Only tets whose four nodes lie on both sides of the
   image plane can hold a pixel; each such tet's cut with the plane is rasterised over its
   bounding box and its pixels found by their barycentric coordinates in the *deformed* tet
   (current node positions). The cost follows the pixels and the cut tets, not the mesh.
2. **What is there.** A pixel's material (rest) coordinate is X = sum of its barycentric
   weights times the tet's rest nodes. A pixel is a lesion where X lies inside a lesion's
   rest sphere (its centre and radius), so a lesion meshed with a handful of tets still
   shows round and of its size; skin where X lies within ``skin_thickness_m`` of the rest
   skin; tissue elsewhere; outside where no tet holds it.
3. **Speckle attached to the material.** Each resolution cell's reflectivity is a circular
   complex Gaussian (fully developed speckle, Goodman 1975: the phasor sum of many
   sub-resolution scatterers): Gaussian values hashed from the integer nodes of a lattice of
   ``scatterer_spacing_m`` in *material* space, interpolated trilinearly at X. The same
   material point gives the same value in every frame, so the speckle moves and stretches
   with the tissue (finite-element-displaced scatterers, Goksel & Salcudean 2009), and an
   echogenicity per label scales it (lesions hypoechoic, skin hyperechoic).
4. **Image formation: the convolution model of speckle** (Bamber & Dickinson 1980; Meunier &
   Bertrand 1995; SonoGym's label-slicing and ``simulate_US_conv``). The RF image is the
   reflectivity convolved with a separable point-spread function: a Gaussian envelope
   (``psf_lateral_m`` and ``psf_axial_m`` full widths at half maximum) modulated axially at
   the centre frequency. On a pixel grid far coarser than a quarter wavelength the carrier
   cannot be sampled, so it is written in its analytic-signal (I/Q baseband) form: the
   carrier's phase at each scatterer, exp(-2ikd), is the random phase the complex
   reflectivity already carries, and the envelope is |reflectivity * Gaussian envelope|
   (a Rayleigh-distributed envelope, as for the RF model's Hilbert envelope). The envelope
   is attenuated with depth d by exp(-2 alpha f d) (two-way, ``attenuation_db_cm_mhz`` at
   ``centre_frequency_mhz``), amplified back by time-gain compensation if it is on, then
   log-compressed over ``dynamic_range_db`` to uint8.

No contact (no coupling medium between the face and the skin) gives an all-black image;
pixels outside the breast are black.

Not modelled: shadowing and enhancement behind lesions, specular reflection at interfaces,
refraction, the elevation beam width (the image samples the plane z = 0 only), electronic
noise, and speckle decorrelation under strain (a material point's speckle never changes).

Modules: ``config`` (:class:`BModeConfig`, the pixel labels), ``imager``
(:class:`BModeImager`), ``kernels`` (the compiled loops). What is checked and measured:
``docs/ultrasound.md``.
"""

from envs.ultrasound.config import LESION_FIRST_LABEL, OUTSIDE, SKIN, TISSUE, BModeConfig
from envs.ultrasound.imager import BModeImager, PlaneSample

__all__ = [
    "LESION_FIRST_LABEL",
    "OUTSIDE",
    "SKIN",
    "TISSUE",
    "BModeConfig",
    "BModeImager",
    "PlaneSample",
]
