"""Cross-batch ("batch-aware") self-attention (paper Sec. Stage 1 Pipeline; Appendix
"More Explanation on the batch-aware self-attention").

The batch holds ``samples x V`` items ordered sample-major: item ``i`` is item
``i % V`` of sample ``i // V`` (the V items of a sample: the intrinsic domains albedo, normal,
roughness, metallic).  In every self-attention layer (diffusers' ``attn1``) each
item's queries attend to the keys/values of all V items of the same sample:

    q_a = W_q z^a,   k_a = W_k (z^a (+) z^n (+) z^r (+) z^m),   v_a = W_v (same concat)

and likewise for n, r, m (appendix equations).  Softmax attention is invariant to
the order of the concatenated keys, so all items can share one concatenation:
reshape (B*V, N, C) -> (B, V*N, C) for q, k and v, run SDPA, reshape back.
Cross-attention (``attn2``, CLIP image embedding) is left per-item.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from diffusers.models.attention_processor import Attention, AttnProcessor2_0


class CrossBatchAttnProcessor:
    """Drop-in replacement for diffusers' ``AttnProcessor2_0`` on self-attention layers.

    Mirrors AttnProcessor2_0 step by step (spatial_norm, 4-D input, group_norm,
    norm_q/norm_k, residual, rescale_output_factor); the only change is that the
    token axis of q, k and v spans the V items of a sample.  With V = 1 it computes
    exactly what AttnProcessor2_0 computes.
    """

    def __init__(self, items_per_sample: int):
        if int(items_per_sample) < 1:
            raise ValueError(f"items_per_sample must be >= 1, got {items_per_sample}")
        self.items_per_sample = int(items_per_sample)

    def __call__(
        self,
        attn: Attention,
        hidden_states: torch.Tensor,
        encoder_hidden_states: torch.Tensor | None = None,
        attention_mask: torch.Tensor | None = None,
        temb: torch.Tensor | None = None,
    ) -> torch.Tensor:
        if encoder_hidden_states is not None:
            raise ValueError(
                "CrossBatchAttnProcessor is for self-attention (attn1) only; "
                "it was called with encoder_hidden_states (a cross-attention layer)"
            )
        if attention_mask is not None:
            raise ValueError(
                "CrossBatchAttnProcessor refuses attention masks: a per-item mask has no meaning across items"
            )
        per_sample = self.items_per_sample
        residual = hidden_states
        if attn.spatial_norm is not None:
            hidden_states = attn.spatial_norm(hidden_states, temb)

        input_ndim = hidden_states.ndim
        if input_ndim == 4:
            batch_size, channel, height, width = hidden_states.shape
            hidden_states = hidden_states.view(batch_size, channel, height * width).transpose(1, 2)
        batch_size, tokens, _ = hidden_states.shape
        if batch_size % per_sample:
            raise ValueError(
                f"cross-batch attention: batch size {batch_size} is not divisible by "
                f"items_per_sample {per_sample} (batch must be samples x items, sample-major)"
            )
        samples = batch_size // per_sample

        if attn.group_norm is not None:
            hidden_states = attn.group_norm(hidden_states.transpose(1, 2)).transpose(1, 2)

        query = attn.to_q(hidden_states)
        key = attn.to_k(hidden_states)
        value = attn.to_v(hidden_states)

        inner_dim = key.shape[-1]
        head_dim = inner_dim // attn.heads

        # (B*V, N, C) -> (B, V*N, heads, d) -> (B, heads, V*N, d): the V items of a sample are
        # contiguous in the batch, so this view() concatenates their tokens (the (+) above).
        def to_heads(x: torch.Tensor) -> torch.Tensor:
            return x.reshape(samples, per_sample * tokens, attn.heads, head_dim).transpose(1, 2)

        query, key, value = to_heads(query), to_heads(key), to_heads(value)
        if attn.norm_q is not None:
            query = attn.norm_q(query)
        if attn.norm_k is not None:
            key = attn.norm_k(key)

        # Same call as AttnProcessor2_0 (default scale 1/sqrt(head_dim)).
        hidden_states = F.scaled_dot_product_attention(
            query, key, value, attn_mask=None, dropout_p=0.0, is_causal=False
        )
        # (B, heads, V*N, d) -> (B, V*N, heads*d) -> (B*V, N, heads*d)
        hidden_states = hidden_states.transpose(1, 2).reshape(batch_size, tokens, attn.heads * head_dim)
        hidden_states = hidden_states.to(query.dtype)

        hidden_states = attn.to_out[0](hidden_states)  # linear proj
        hidden_states = attn.to_out[1](hidden_states)  # dropout

        if input_ndim == 4:
            hidden_states = hidden_states.transpose(-1, -2).reshape(batch_size, channel, height, width)
        if attn.residual_connection:
            hidden_states = hidden_states + residual
        return hidden_states / attn.rescale_output_factor


def set_cross_batch_attention(unet: torch.nn.Module, items_per_sample: int | None) -> int:
    """Install ``CrossBatchAttnProcessor(items_per_sample)`` on every self-attention layer
    (processor names ending in "attn1.processor"); ``items_per_sample`` None or 1 installs
    diffusers' ``AttnProcessor2_0`` on every layer (the ablation: independent items).
    Returns the number of self-attention layers set to cross-batch (0 for the ablation).
    """
    processors = unet.attn_processors
    if items_per_sample is None or int(items_per_sample) == 1:
        unet.set_attn_processor({name: AttnProcessor2_0() for name in processors})
        return 0
    cross = CrossBatchAttnProcessor(int(items_per_sample))
    new = {name: (cross if name.endswith("attn1.processor") else AttnProcessor2_0()) for name in processors}
    changed = sum(name.endswith("attn1.processor") for name in processors)
    if changed == 0:
        raise ValueError("set_cross_batch_attention: the model has no self-attention (attn1) layers")
    unet.set_attn_processor(new)
    return changed
