"""Stray light: lens scattering as a convolution of the complex image on the sensor.

Model (Mure-Dubois and Huegli 2007): ``S_meas = (delta + h) * S`` for every modulation
frequency and harmonic (and for the unmodulated light as well: the lens scatters all of it).
``h`` moves a fraction ``W`` of each pixel's light elsewhere:

    h = sum_i w_i G_i  +  veil  +  ghost  +  measured  -  W delta     (conserve = true)

with ``W = sum_i w_i + w_veil + w_ghost + w_measured`` (the *fraction of light scattered*).
Each scattering component is normalised to unit sum over the infinite plane, so a weight is
exactly the fraction of a pixel's light the component moves; light scattered beyond the
sensor edge is lost, as in a real camera. With ``conserve = false`` the scattered light is
added on top (``S + sum_i w_i G_i * S + ...``), Mure-Dubois and Huegli's additive form.

Components:
- Gaussians: weight, ``sigma_x``, ``sigma_y`` in pixels, integrated over each pixel's area
  (erf differences), so small sigmas are exact.
- Veil: a weight spread uniformly over the whole sensor (every pixel receives
  ``w_veil * sum(S) / (H W)``).
- Ghosts: a reflection between lens surfaces images the scene mirrored through a centre
  ``c`` (each ghost's own, default the principal point): light at pixel ``p`` leaks to
  ``2c - p`` (sub-pixel), blurred by a Gaussian.
- Measured PSF: the image of a point source (any size; its peak pixel is the direct light).

Convolutions are linear, never circular: images are zero-padded for the FFT so that no
wrap-around reaches the retained pixels. The shift-invariant part uses a kernel of shape
``[2H-1, 2W-1]`` (every shift between two sensor pixels) centred at ``(H-1, W-1)``. The
operators are public (``psf_kernel``, ``ghost_kernel``, ``convolve``, ``correlate``,
``StrayLightOperator`` with ``apply``/``scatter``/``adjoint``/``invert``) so corrections
(``eval/corrections``) are built on them. ``StrayLightPSF`` is the one PSF type: simulated
(the ``stray_light`` effect's parameters, ``from_params``/``to_params``), diagnosed,
calibrated, saved and loaded (``save``/``load``, JSON) and corrected with.

Modules (everything is importable from ``tofhil.sim.straylight`` itself):

- :mod:`.psf`: the PSF type (:class:`StrayLightPSF`, its lobes and ghosts), its parameter
  mapping and its file;
- :mod:`.kernels`: pixel-integrated Gaussians, the PSF's and the ghosts' kernels, the radial
  lobe's hat functions;
- :mod:`.convolution`: the padded FFT convolution and its adjoint;
- :mod:`.scattering`: :class:`StrayLightOperator` (forward, stray part, adjoint, inverse);
- :mod:`.lobes`: the fast path of Gaussian lobes and a veil, with its content-keyed caches.
"""

from tofhil.sim.straylight.convolution import PaddedConvolution, convolve, correlate, fft_shape, flip_image
from tofhil.sim.straylight.kernels import (field_rho2, gaussian_kernel, ghost_kernel, ghost_shift, psf_kernel,
                                           radial_hat_sums, radial_hats, shift_grid)
from tofhil.sim.straylight.lobes import GaussianBlur, apply_lobes, lobes_only
from tofhil.sim.straylight.lobes import _BLURS as _BLURS, _SCATTERED as _SCATTERED  # (the fast path's caches)
from tofhil.sim.straylight.psf import (PSF_FORMAT, PSF_KEYS, GaussianLobe, Ghost, RadialProfile, StrayLightPSF,
                                       load_psf_image)
from tofhil.sim.straylight.scattering import StrayLightOperator, apply_stray_light

__all__ = ["GaussianBlur", "GaussianLobe", "Ghost", "PSF_FORMAT", "PSF_KEYS", "PaddedConvolution", "RadialProfile",
           "StrayLightOperator", "StrayLightPSF", "apply_lobes", "apply_stray_light", "convolve", "correlate",
           "fft_shape", "field_rho2", "flip_image", "gaussian_kernel", "ghost_kernel", "ghost_shift", "load_psf_image",
           "lobes_only", "psf_kernel", "radial_hat_sums", "radial_hats", "shift_grid"]
