"""`shard:` section of params.yaml (pilight.params imports this class from here)."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field, field_validator


class ShardParams(BaseModel):
    """How renders become webdataset shards and which relighting pairs stage 2 sees."""

    model_config = ConfigDict(extra="forbid")

    maxcount: int = Field(
        1000,
        description="Most samples (one per scene, view, light) in one shard. Shards roll over only "
        "between views, so all lights of a view share a shard (stage 2 pairs them while streaming); "
        "a single view with more lights than maxcount gets a shard of its own.",
    )
    maxsize: int = Field(
        500_000_000,
        description="Most payload bytes in one shard (same view-boundary rule). webdataset advises "
        "100 MB - 1 GB: fewer, larger shards read faster; more shards spread over more workers.",
    )
    pairs_per_view: int | None = Field(
        None,
        description="Relighting pairs (light a -> light b, a != b) drawn per view, deterministically "
        "from base.seed; null = all L * (L - 1) ordered pairs. Identity pairs are extra.",
    )
    identity_pairs: bool = Field(
        True,
        description="Also list a -> a for every light: the paper's reconstruction setting.",
    )

    @field_validator("maxcount")
    @classmethod
    def _positive_count(cls, v: int) -> int:
        if v < 1:
            raise ValueError(f"shard.maxcount must be >= 1 sample per shard, got {v}")
        return v

    @field_validator("maxsize")
    @classmethod
    def _positive_size(cls, v: int) -> int:
        if v < 1:
            raise ValueError(f"shard.maxsize must be a positive number of bytes, got {v}")
        return v

    @field_validator("pairs_per_view")
    @classmethod
    def _pairs(cls, v: int | None) -> int | None:
        if v is not None and v < 0:
            raise ValueError(f"shard.pairs_per_view must be >= 0 or null (all pairs), got {v}")
        return v
