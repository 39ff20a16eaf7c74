"""The human eye as a parametric, differentiable aperture.

Two images make up the eye's aperture, as in Kakimoto et al. (2004):

* the **pupil function** ``P``: the pupil opening and the structures inside the eye
  that sit (after projection) in the pupil plane: cornea cells, lens-nucleus and
  vitreous particles, lens-fibre gratings (Ritschel et al. 2009, sec. 3);
* the **obstacle image** ``t_o``: the eyelids and eyelashes in front of the eye.

The glare is ``|F[t_o * P]|**2`` (Kakimoto eq. 5, a fixed mask); for the
position-dependent glare of their eq. 3 the obstacle image is translated
relative to the pupil (:meth:`EyeAperture.obstacle_transmission` with `shift_mm`).

**Units and frame.** Lengths in mm in the pupil plane, angles in degrees
counter-clockwise from +x towards +y; the grid's origin (index ``npix // 2``) is
the eye's axis; y points up (the upper lid is at ``y > 0``). See
:class:`~invglare._core.grids.ApertureGrid`.

**Relaxed counts.** Lashes, particles and gratings are drawn as a fixed pool of
`n_max` elements from an explicit `jax.random` key; element `i` is weighted by
``smooth_step(count - i)`` (a cubic step from 0 at ``count = i`` to 1 at
``count = i + 1``). At an integer count exactly that many elements are present;
in between, one element fades in. Element `i`'s random numbers come from
``fold_in(key, i)``, so they do not depend on `n_max`: growing the pool keeps
the existing elements. The draws are *unit* random numbers (uniform or standard
normal) scaled by the parameters, so gradients reach spreads, lengths and sizes.
The derivative with respect to a count is 0 at exact integers (the step is
flat at both ends); start a fit at a non-integer count. (:mod:`.pool`)

**Stamps.** Particles, grating lines and lash segments are rasterised on small
local windows (:mod:`invglare.aperture.stamps`): an element costs its own size in
pixels squared, not the grid's area (a lash, being long, costs its length times a
window a few widths across). The window size is a static shape: it is computed from
concrete parameters and the grid pitch, or fixed beforehand with
:meth:`EyeAperture.with_stamp_windows` for use inside `jit` / `grad` / `vmap` over
element sizes or a traced grid.

**Modules.** :mod:`.pupil` (:class:`Pupil`, :class:`Eyelids`), :mod:`.lashes`
(:class:`Eyelashes`), :mod:`.inclusions` (:class:`Particles`, :class:`Gratings`),
:mod:`.aperture` (:class:`EyeAperture`), :mod:`.pool` (relaxed counts, draws, stamp
windows), :mod:`.schema` (the config tables and :func:`eye_to_config`), :mod:`.presets`
(:func:`lashed_daylight_eye`, :func:`night_eye`). The reader of eye tables is
:func:`invglare.config.eye.eye_from_config`.
"""

from invglare.aperture.eye.aperture import EyeAperture as EyeAperture
from invglare.aperture.eye.inclusions import REGIONS as REGIONS
from invglare.aperture.eye.inclusions import Gratings as Gratings
from invglare.aperture.eye.inclusions import Particles as Particles
from invglare.aperture.eye.lashes import Eyelashes as Eyelashes
from invglare.aperture.eye.pool import relaxed_weights as relaxed_weights
from invglare.aperture.eye.pool import smooth_step as smooth_step
from invglare.aperture.eye.presets import daylight_eye as daylight_eye
from invglare.aperture.eye.presets import lashed_daylight_eye as lashed_daylight_eye
from invglare.aperture.eye.presets import night_eye as night_eye
from invglare.aperture.eye.pupil import LIDS as LIDS
from invglare.aperture.eye.pupil import Eyelids as Eyelids
from invglare.aperture.eye.pupil import Pupil as Pupil
from invglare.aperture.eye.schema import EYE_KEYS as EYE_KEYS
from invglare.aperture.eye.schema import eye_to_config as eye_to_config
