"""The image pipeline: bright pixels, FFT convolution, billboards, tone mapping, scenes.

A glare render is: find the bright pixels of a linear HDR image (`bright_pixels`,
`bright_pixel_list`), spread them with the glare PSF (`convolve_psf` over the
whole frame, or `billboard_glare` stamps at a list of pixels, optionally with a
PSF per position: `position_glare` gives each light of a frame the Kakimoto PSF of its
own direction), add the result to the image and tone-map it for display
(`tonemap` and `TONEMAPS`); or, as Kakimoto et al. composite, tone-map each glare into a
billboard and blend it onto the low-dynamic-range picture (`composite`). `scenes` provides
small procedural HDR scenes in cd/m^2 so that all of this runs with nothing downloaded.
`temporal_frames` renders the temporal glare model's animations (`render_frame`,
`render_sequence`: a per-frame PSF convolved with an HDR frame and tone-mapped, one
`lax.scan` per sequence).
"""

from invglare.render.billboard import add_billboards as add_billboards
from invglare.render.billboard import billboard_glare as billboard_glare
from invglare.render.billboard import replace_with_billboards as replace_with_billboards
from invglare.render.bright import REC709_WEIGHTS as REC709_WEIGHTS
from invglare.render.bright import BrightPixels as BrightPixels
from invglare.render.bright import bright_pixel_list as bright_pixel_list
from invglare.render.bright import bright_pixels as bright_pixels
from invglare.render.bright import light_angles_deg as light_angles_deg
from invglare.render.bright import luminance as luminance
from invglare.render.composite import kakimoto_billboard_texture as kakimoto_billboard_texture
from invglare.render.composite import kakimoto_composite as kakimoto_composite
from invglare.render.convolve import check_compatible_scales as check_compatible_scales
from invglare.render.convolve import convolve_psf as convolve_psf
from invglare.render.convolve import fft_size as fft_size
from invglare.render.convolve import linear_period as linear_period
from invglare.render.convolve import resample_psf as resample_psf
from invglare.render.position_glare import position_psf_bank as position_psf_bank
from invglare.render.position_glare import render_position_glare as render_position_glare
from invglare.render.scenes import SCENES as SCENES
from invglare.render.scenes import candle as candle
from invglare.render.scenes import street_lights_at_night as street_lights_at_night
from invglare.render.scenes import sunlit_specular_highlight as sunlit_specular_highlight
from invglare.render.scenes import validate_scene as validate_scene
from invglare.render.scenes import write_scene as write_scene
from invglare.render.temporal_frames import render_frame as render_frame
from invglare.render.temporal_frames import render_sequence as render_sequence
from invglare.render.tonemap import DISPLAY_MAX as DISPLAY_MAX
from invglare.render.tonemap import TONEMAPS as TONEMAPS
from invglare.render.tonemap import GlareLayers as GlareLayers
from invglare.render.tonemap import display_to_unit as display_to_unit
from invglare.render.tonemap import exposure_gamma as exposure_gamma
from invglare.render.tonemap import kakimoto_glare_image as kakimoto_glare_image
from invglare.render.tonemap import kakimoto_glare_layers as kakimoto_glare_layers
from invglare.render.tonemap import kakimoto_scene_scale as kakimoto_scene_scale
from invglare.render.tonemap import kakimoto_sigmoid as kakimoto_sigmoid
from invglare.render.tonemap import kakimoto_sigmoid_inverse as kakimoto_sigmoid_inverse
from invglare.render.tonemap import kakimoto_tonemap as kakimoto_tonemap
from invglare.render.tonemap import log_average_luminance as log_average_luminance
from invglare.render.tonemap import reinhard_display as reinhard_display
from invglare.render.tonemap import reinhard_global as reinhard_global
from invglare.render.tonemap import srgb_display as srgb_display
from invglare.render.tonemap import srgb_encode as srgb_encode
from invglare.render.tonemap import tonemap as tonemap
