"""Inverse camera response U from an exposure sweep of a static scene (Eq. 5-7).

Image formation (Eq. 3-4): ``I_i(x) = C(t_i E(x))``, i.e. ``U(I_i(x)) = t_i E(x)`` with
``U = C^{-1}``. Each band is its own camera. The paper estimates U and E by minimising

    (Eq. 5)  M(U, E) = sum_i sum_x (U(I_i(x)) - t_i E(x))^2

alternating its two closed-form minimisers

    (Eq. 6)  U(k) = sum_{(i,x) in Omega_k} t_i E(x) / |Omega_k|,  Omega_k = {(i, x): I_i(x) = k}
    (Eq. 7)  E(x) = sum_i t_i U(I_i(x)) / sum_i t_i^2

This plain alternation is kept as ``method="alternating"``. It treats the noise as if it were
on ``U(I)`` while it is on the DN, and converges to a biased fixed point (PAPER.md measured
13-24 % worst error in U on its 10-bit sweeps; 3-5 % on the synthetic sweeps of our tests).

The default ``method="forward"`` models the noise where it is. It fits the forward response
``C`` (monotone piecewise linear in the exposure energy ``x``: ``C(0)`` plus segment slopes
``>= 0``, knots at even DN steps, a smoothness prior) and ``E`` per pixel by weighted least
squares on the DN:

    M(C, E) = sum_i sum_x w_ix (I_i(x) - C(t_i E(x)))^2 + censored terms + prior(C),
    w = rho_ix / var_ix,  var = a + b (C(t_i E(x)) - black) + c g_ix^2

Each iteration takes (b) the C update given E, the errors-in-DN analogue of Eq. 6, which is
a bounded linear least-squares problem because C is linear in its parameters, jointly with
(a) the E update of every pixel linearised (the Eq. 7 analogue), E eliminated through its
Schur complement (a Gauss-Newton step on both, with backtracking), then a per-pixel
Gauss-Newton step on E alone. Finally ``U = C^{-1}`` on the DN grid; ``C(0)`` is the
estimated black level, so ``U = 0`` there.

Photographs (8-bit JPEG brackets, handheld) break the clean-sweep assumptions of Eq. 5 in
ways the fit handles explicitly (measured on ``pipeline.sim.world.photo``):

- noise model ``var``: read + shot noise ``a + b mu`` plus ``c g^2``, ``g`` the sample's local
  DN gradient (neighbours in the band): a camera shifted by ``s`` pixels between frames moves
  a sample by about ``s g``, so ``c`` (a mean squared shift, 0 on a tripod) is estimated
  from the residuals and edges weigh less where the frames are misaligned; ``a, b, c`` from
  robust (median) binned squared residuals, leverage corrected;
- outliers ``rho``: samples more than 3 standard deviations off the curve taper to weight 0
  at 6 (moving things, parallax, JPEG ringing); Gaussian noise keeps full weight;
- ceilings: a pixel's samples from its first saturated exposure on, or from a value in the
  upper half that a clearly longer exposure does not exceed (stuck below the clip: a colour
  channel clipped before the camera's colour matrix), are not points of the curve;
- censoring: DN 0 (where the neighbours are dark too: a 0 next to an edge is more often a
  shifted edge or a colour-matrix / chroma artefact) and a pixel's first saturated sample
  are censored observations (Tobit terms ``-2 log Phi``, as Newton pseudo-observations), not
  dropped: dropping them keeps only the noise draws that stayed inside the range, biased
  towards mid-range (a black level above 0 and a too flat shoulder);
- hidden saturation: in JPEG photographs a blown highlight is partly 245-254 (ringing);
  where such samples are common the top of U follows the paper's Eq. 6 in the log domain
  (``_noise.hidden_saturation_top``);
- prior: second differences of ``log C'`` against ``log x`` with the best power law projected
  out (every gamma curve and the linear sensor are free), weighted adaptively: the exposure
  ratios of a bracket are powers of one step, which leaves U determined by the data only
  up to a factor periodic in ``log x`` with that step (:func:`exposure_period`), so the
  weight grows with the step squared (2 frames 4 stops apart need a strong prior) and with
  the cube of the robust noise relative to the DN range (misfit of JPEG, sharpening and
  misalignment is absorbed by the prior rather than by wiggles of C).

Large bands (the pipeline passes every pixel, e.g. 9 frames x 24 Mpx) are thinned to a seeded
random subset of candidate pixels before anything else: no full-size temporaries or copies.

Gauge (docs/architecture.md): ``U[k] = 0`` at/below black, ``U[k_ref] = k_ref - black`` with
``k_ref = dn_max // 2``. Saturated (``>= saturation_dn``, default ``dn_max``) and clipped
(``0``) samples enter only as censored terms; DN never observed are filled monotonically
(linear extrapolation above the highest observed DN).

Layout of the package (a newcomer reads them in this order):

- ``_fit``: the front door, :func:`fit_response` and :func:`fit_response_alternating`: check
  the sweep, choose pixels and masks, run the chosen method;
- ``_common``: what every method shares: :class:`ResponseFit`, the sweep masks, the gauge
  (``finalise``), :func:`predict_dn`, :func:`predict_heldout_rms`, :func:`residual_profile`;
- ``_consistency``: :func:`check_exposure_consistency`, run before every fit;
- ``_alternating``: the paper's plain Eq. 6/7;
- ``_forward``: the default errors-in-DN fit and :func:`exposure_period`, built on
  ``_curve`` (the forward response C and its least-squares steps) and ``_noise`` (noise
  model, outlier weights, censored and hidden-saturated samples).
- ``_uncertainty``: how far U can be trusted at each DN (:func:`response_uncertainty`: one
  reading's noise through U's slope and the fit's own standard deviation of ``log U``, from
  its information matrix with E marginalised, with how far U moves when the smoothness prior
  is :data:`PRIOR_RELAX` times weaker), given by the forward method.

References
----------
.. [1] R. Khanna, I. Sa, J. Nieto and R. Siegwart, "On Field Radiometric Calibration
       for Multispectral Cameras", IEEE International Conference on Robotics and
       Automation (ICRA), 2017.
.. [2] P. E. Debevec and J. Malik, "Recovering High Dynamic Range Radiance Maps from
       Photographs", Proc. SIGGRAPH 1997.
"""

from ._common import CANDIDATES_PER_PIXEL, RESIDUAL_BINS, ResponseFit, predict_dn, predict_heldout_rms, residual_profile
from ._consistency import check_exposure_consistency
from ._fit import CENSOR_LOW_MAX_GRADIENT, METHODS, PRIORS, fit_response, fit_response_alternating
from ._forward import ADAPT_FROM, PERIOD_POW, PERIOD_REF, PRIOR_RELAX, SIGMA_MAX, SIGMA_POW, SIGMA_REF, exposure_period
from ._noise import HIDDEN_FRACTION, HIDDEN_FROM, OUTLIER_Z
from ._uncertainty import response_uncertainty

__all__ = [
    "ADAPT_FROM",
    "CANDIDATES_PER_PIXEL",
    "CENSOR_LOW_MAX_GRADIENT",
    "HIDDEN_FRACTION",
    "HIDDEN_FROM",
    "METHODS",
    "OUTLIER_Z",
    "PERIOD_POW",
    "PERIOD_REF",
    "PRIORS",
    "PRIOR_RELAX",
    "RESIDUAL_BINS",
    "SIGMA_MAX",
    "SIGMA_POW",
    "SIGMA_REF",
    "ResponseFit",
    "check_exposure_consistency",
    "exposure_period",
    "fit_response",
    "fit_response_alternating",
    "predict_dn",
    "predict_heldout_rms",
    "residual_profile",
    "response_uncertainty",
]
