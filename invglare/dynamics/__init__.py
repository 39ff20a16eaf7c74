"""Time: how the eye moves while it looks at a bright scene (Ritschel et al. 2009, sec. 3).

Pure functions of ``(time, key, parameters)`` and a small state carried from frame to
frame; nothing here imports the apertures (the temporal glare model applies the
numbers to an eye).

- :mod:`~invglare.dynamics.pupil`: mean pupil from the field luminance (eq. 2), hippus (eq. 1);
- :mod:`~invglare.dynamics.accommodation`: accommodation micro-fluctuations;
- :mod:`~invglare.dynamics.lens`: the 17 x 17 mass-spring lens that moves lens particles;
- :mod:`~invglare.dynamics.vitreous`: the vitreous rigid body shaken by saccades;
- :mod:`~invglare.dynamics.lids`: blinking and squinting;
- :mod:`~invglare.dynamics.eye`: all of them as one state and one step;
- :mod:`~invglare.dynamics.noise`: three-octave value noise.

Every module says where its numbers come from ("Where the numbers come from"): the
paper's (and its sources': Moon and Spencer, Fry, Gray et al., Zimmerman), textbook
anatomy, or values chosen here, named as such. The observer's motion, which the paper
lists among the forces on the vitreous, is an input of each step
(``head_acceleration_rad_s2``).
"""

from invglare.dynamics.accommodation import HIGH_BAND_HZ as HIGH_BAND_HZ
from invglare.dynamics.accommodation import LOW_BAND_MAX_HZ as LOW_BAND_MAX_HZ
from invglare.dynamics.accommodation import Accommodation as Accommodation
from invglare.dynamics.eye import DynamicsState as DynamicsState
from invglare.dynamics.eye import EyeDynamics as EyeDynamics
from invglare.dynamics.eye import FrameValues as FrameValues
from invglare.dynamics.lens import LensMesh as LensMesh
from invglare.dynamics.lens import LensState as LensState
from invglare.dynamics.lids import LidMotion as LidMotion
from invglare.dynamics.noise import value_noise as value_noise
from invglare.dynamics.pupil import P_MAX_MM as P_MAX_MM
from invglare.dynamics.pupil import PupilDynamics as PupilDynamics
from invglare.dynamics.pupil import damp_luminance as damp_luminance
from invglare.dynamics.pupil import hippus_diameter_mm as hippus_diameter_mm
from invglare.dynamics.pupil import hippus_scale as hippus_scale
from invglare.dynamics.pupil import max_hippus_amplitude_mm as max_hippus_amplitude_mm
from invglare.dynamics.pupil import moon_spencer_diameter_mm as moon_spencer_diameter_mm
from invglare.dynamics.vitreous import VitreousBody as VitreousBody
from invglare.dynamics.vitreous import VitreousState as VitreousState
from invglare.dynamics.vitreous import rotation_matrix as rotation_matrix
