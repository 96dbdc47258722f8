"""PI-Light's diffusion model: codecs, UNet, cross-batch attention, conditioning,
v-prediction schedule, the domain-labelled denoiser and its sampler (paper Sec. Stage 1)."""

from .attention import CrossBatchAttnProcessor, set_cross_batch_attention
from .codec import Codec, PixelCodec, VaeCodec, make_codec
from .conditioning import ClipImageEmbedding, LearnedEmbedding, make_conditioning, null_like
from .model import DomainDiffusion
from .sampler import sample
from .schedule import make_train_scheduler, v_to_eps, v_to_x0
from .unet import PAPER_UNET_SPEC, UNetSpec, build_unet, load_pretrained_unet

__all__ = [
    "CrossBatchAttnProcessor",
    "set_cross_batch_attention",
    "Codec",
    "PixelCodec",
    "VaeCodec",
    "make_codec",
    "ClipImageEmbedding",
    "LearnedEmbedding",
    "make_conditioning",
    "null_like",
    "DomainDiffusion",
    "sample",
    "make_train_scheduler",
    "v_to_eps",
    "v_to_x0",
    "PAPER_UNET_SPEC",
    "UNetSpec",
    "build_unet",
    "load_pretrained_unet",
]
