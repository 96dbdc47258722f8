"""v-prediction algebra (schedule.py): exact round trips, zero-SNR terminal step."""

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from pilight.diffusion.schedule import make_train_scheduler, v_to_eps, v_to_x0

SCHED = make_train_scheduler()
T = SCHED.config.num_train_timesteps


def _round_trip(sched, t, seed=0):
    g = torch.Generator().manual_seed(seed)
    x0 = torch.randn(len(t), 3, 4, 4, generator=g)
    noise = torch.randn(len(t), 3, 4, 4, generator=g)
    ac = sched.alphas_cumprod
    x_t = sched.add_noise(x0, noise, t)
    v = sched.get_velocity(x0, noise, t)  # the training target of both stages
    return x0, noise, x_t, v, ac


def test_scheduler_is_v_prediction_without_clipping():
    assert SCHED.config.prediction_type == "v_prediction"
    assert SCHED.config.clip_sample is False


def test_round_trip_at_both_ends():
    t = torch.tensor([0, T - 1, 0, T - 1])
    x0, noise, x_t, v, ac = _round_trip(SCHED, t)
    torch.testing.assert_close(v_to_x0(x_t, v, ac, t), x0, atol=1e-5, rtol=0)
    torch.testing.assert_close(v_to_eps(x_t, v, ac, t), noise, atol=1e-5, rtol=0)


@settings(max_examples=30, deadline=None)
@given(st.lists(st.integers(0, T - 1), min_size=1, max_size=6), st.integers(0, 2**31 - 1))
def test_round_trip_random_t(ts, seed):
    t = torch.tensor(ts)
    x0, noise, x_t, v, ac = _round_trip(SCHED, t, seed)
    torch.testing.assert_close(v_to_x0(x_t, v, ac, t), x0, atol=1e-5, rtol=0)
    torch.testing.assert_close(v_to_eps(x_t, v, ac, t), noise, atol=1e-5, rtol=0)


def test_zero_snr_terminal_step():
    sched = make_train_scheduler(rescale_zero_snr=True, timestep_spacing="trailing")
    assert sched.alphas_cumprod[-1].item() == 0.0
    t = torch.full((2,), T - 1)
    x0, noise, x_t, v, ac = _round_trip(sched, t)
    torch.testing.assert_close(x_t, noise)  # pure noise at the terminal step
    out = v_to_x0(x_t, v, ac, t)
    assert torch.isfinite(out).all()
    torch.testing.assert_close(out, -v)
    torch.testing.assert_close(out, x0, atol=1e-5, rtol=0)


def test_rejects_scalar_t():
    x = torch.zeros(2, 3, 4, 4)
    try:
        v_to_x0(x, x, SCHED.alphas_cumprod, torch.tensor(5))
    except ValueError as e:
        assert "one timestep per sample" in str(e)
    else:
        raise AssertionError("expected ValueError")


def test_sample_timesteps_terminal_fraction():
    from pilight.diffusion.schedule import sample_timesteps

    T = 1000  # noqa: N806 (the paper's T)
    # Fraction 0 draws exactly the uniform stream it always drew (old runs resume bit-identically).
    assert torch.equal(
        sample_timesteps(64, T, 0.0, torch.Generator().manual_seed(3)),
        torch.randint(0, T, (64,), generator=torch.Generator().manual_seed(3)),
    )
    assert (sample_timesteps(64, T, 1.0, torch.Generator().manual_seed(3)) == T - 1).all()
    t = sample_timesteps(20000, T, 0.5, torch.Generator().manual_seed(3))
    assert t.min() >= 0 and t.max() == T - 1
    assert abs(float((t == T - 1).float().mean()) - 0.5) < 0.02  # 0.5 + the uniform 1/T
    with pytest.raises(ValueError, match="terminal_fraction"):
        sample_timesteps(4, T, 1.5)
