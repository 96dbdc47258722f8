"""DomainDiffusion (model.py) and the sampler (sampler.py)."""

import pytest
import torch

from fixtures.tiny_unet import TINY
from pilight.diffusion.conditioning import LearnedEmbedding
from pilight.diffusion.model import DomainDiffusion
from pilight.diffusion.sampler import sample
from pilight.diffusion.schedule import make_train_scheduler
from pilight.diffusion.unet import build_unet

LATENT, COND, DOMAINS = 4, 6, 4


def _model(cross_batch=True, views=4, terminal_timestep=None):
    torch.manual_seed(0)
    unet = build_unet(TINY, in_channels=LATENT + COND, out_channels=LATENT, num_domains=DOMAINS)
    return DomainDiffusion(
        unet,
        LearnedEmbedding(16),
        DOMAINS,
        COND,
        items_per_sample=views,
        cross_batch=cross_batch,
        terminal_timestep=terminal_timestep,
    ).eval()


def test_cfg_dropout_gives_dropped_samples_the_null_state():
    """condition_states: the samples flagged in ``drop`` (classifier-free guidance's dropout, and its
    unconditional branch) get the null state, zeros; the others keep their embedding."""
    model = _model()
    images = torch.rand(3, COND, 8, 8)
    kept = model.condition_states(images)
    assert kept.abs().sum() > 0
    out = model.condition_states(images, torch.tensor([True, False, True]))
    assert torch.equal(out[0], torch.zeros_like(out[0])) and torch.equal(out[2], torch.zeros_like(out[2]))
    assert torch.equal(out[1], kept[1])


def _inputs(samples, views, seed=0):
    g = torch.Generator().manual_seed(seed)
    n = samples * views
    cond = torch.randn(samples, COND, 8, 8, generator=g).repeat_interleave(views, 0)  # same image for all views
    ids = torch.arange(views).repeat(samples)
    ehs = torch.randn(samples, 1, 16, generator=g).repeat_interleave(views, 0)
    return cond, ids, ehs, n


def test_forward_shapes_padding_and_bf16():
    model = _model()
    cond, ids, ehs, n = _inputs(2, 4)
    x, t = torch.randn(n, LATENT, 8, 8), torch.full((n,), 300)
    with torch.no_grad():
        v = model(x, cond, t, ids, ehs)
        assert v.shape == (n, LATENT, 8, 8)
        # a narrower condition (a Stage 2 branch with fewer inputs) is zero-padded on channels
        narrow = model(x, cond[:, :2], t, ids, ehs)
        padded = model(x, torch.cat([cond[:, :2], torch.zeros(n, 4, 8, 8)], 1), t, ids, ehs)
        assert torch.equal(narrow, padded)
        with torch.autocast("cpu", dtype=torch.bfloat16):
            v16 = model(x, cond, t, ids, ehs)
    assert v16.dtype == torch.bfloat16 and torch.isfinite(v16).all()


def test_forward_errors_name_numbers():
    model = _model()
    cond, ids, ehs, n = _inputs(1, 4)
    x, t = torch.randn(n, LATENT, 8, 8), torch.full((n,), 3)
    with pytest.raises(ValueError, match=r"48 channels.*predicts 4"):
        model(torch.randn(n, 48, 8, 8), cond, t, ids, ehs)
    with pytest.raises(ValueError, match=r"7 channels.*at most 6"):
        model(x, torch.randn(n, 7, 8, 8), t, ids, ehs)
    with pytest.raises(ValueError, match="domain_ids"):
        model(x, cond, t, ids + 1, ehs)
    with pytest.raises(ValueError, match="items_per_sample"):
        model(x[:3], cond[:3], t[:3], ids[:3], ehs[:3])
    with pytest.raises(ValueError, match=r"cross_attention_dim is 16"):
        DomainDiffusion(model.unet, LearnedEmbedding(8), DOMAINS, COND)
    with pytest.raises(ValueError, match=r"latent \(4\) \+ condition \(5\)"):
        DomainDiffusion(model.unet, LearnedEmbedding(16), DOMAINS, 5)


def test_deterministic_with_seed_and_modes():
    model = _model()
    cond, ids, ehs, _ = _inputs(2, 4)
    run = lambda seed, **kw: sample(
        model, cond, ids, ehs, items_per_sample=4, generator=torch.Generator().manual_seed(seed), **kw
    )
    a, b = run(0, steps=3), run(0, steps=3)
    assert a.shape == (8, LATENT, 8, 8) and torch.equal(a, b)
    assert not torch.equal(a, run(1, steps=3))
    # trailing DDIM with one step is exactly the single-step x0 prediction at t = T-1
    torch.testing.assert_close(run(0, steps=1), run(0, mode="single_step"), atol=1e-5, rtol=0)
    zero_snr = make_train_scheduler(rescale_zero_snr=True, timestep_spacing="trailing").config
    for mode in ("ddim", "single_step"):
        assert torch.isfinite(run(0, steps=2, mode=mode, scheduler_config=zero_snr)).all()


def test_cfg_groups_cond_and_uncond_separately():
    model = _model()
    cond, ids, ehs, n = _inputs(2, 4)
    noise = torch.randn(n, LATENT, 8, 8, generator=torch.Generator().manual_seed(3))
    null = torch.randn_like(ehs)
    s = 3.0
    out = sample(
        model, cond, ids, ehs, items_per_sample=4, mode="single_step", cfg_scale=s, noise=noise, null_hidden_states=null
    )
    # reference: two separate (unbatched) calls
    sched = make_train_scheduler()
    t = torch.full((n,), 999)
    with torch.no_grad():
        v_c = model(noise, cond, t, ids, ehs)
        v_u = model(noise, torch.zeros_like(cond), t, ids, null)
    v = v_u + s * (v_c - v_u)
    a = sched.alphas_cumprod[999]
    torch.testing.assert_close(out, a.sqrt() * noise - (1 - a).sqrt() * v, atol=1e-5, rtol=1e-5)


def test_ensemble_is_mean_of_members():
    model = _model()
    cond, ids, ehs, n = _inputs(1, 4)
    noise = torch.randn(3 * n, LATENT, 8, 8, generator=torch.Generator().manual_seed(5))
    out = sample(model, cond, ids, ehs, items_per_sample=4, steps=2, ensemble=3, noise=noise)
    members = [
        sample(model, cond, ids, ehs, items_per_sample=4, steps=2, noise=noise[k * n : (k + 1) * n]) for k in range(3)
    ]
    torch.testing.assert_close(out, torch.stack(members).mean(0), atol=1e-5, rtol=1e-5)
    with pytest.raises(ValueError, match="noise must have shape"):
        sample(model, cond, ids, ehs, items_per_sample=4, ensemble=2, noise=noise)


@pytest.mark.parametrize("cross_batch", [False, True])
def test_domain_subset_differs_only_by_cross_view_attention(cross_batch):
    """Albedo alone (V=1) vs all four domains (V=4) from the same albedo noise: identical
    plumbing, so without cross-batch attention the albedo output is the same; with it, the
    other views change the albedo."""
    model = _model(cross_batch=cross_batch)
    cond, ids, ehs, n = _inputs(1, 4)
    noise = torch.randn(n, LATENT, 8, 8, generator=torch.Generator().manual_seed(7))
    all4 = sample(model, cond, ids, ehs, items_per_sample=4, steps=2, noise=noise)
    albedo = sample(model, cond[:1], ids[:1], ehs[:1], items_per_sample=1, steps=2, noise=noise[:1])
    assert albedo.shape == (1, LATENT, 8, 8)
    assert model.items_per_sample == 4  # the sampler restores the model's grouping
    if cross_batch:
        assert (all4[:1] - albedo).abs().max() > 1e-4
    else:
        torch.testing.assert_close(all4[:1], albedo, atol=1e-5, rtol=1e-5)


def test_model_keeps_installed_attention_and_set_views_is_reversible():
    from pilight.diffusion.attention import set_cross_batch_attention

    torch.manual_seed(0)
    unet = build_unet(TINY, in_channels=LATENT + COND, out_channels=LATENT, num_domains=DOMAINS)
    set_cross_batch_attention(unet, None)  # the ablation, chosen before the model is built
    model = DomainDiffusion(unet, LearnedEmbedding(16), DOMAINS, COND)
    assert not model.cross_batch and model.items_per_sample == DOMAINS

    set_cross_batch_attention(unet, 2)
    model = DomainDiffusion(unet, LearnedEmbedding(16), DOMAINS, COND)
    assert model.cross_batch and model.items_per_sample == 2
    model.set_items_per_sample(1)  # one domain at a time: same math as vanilla, but stays switchable
    model.set_items_per_sample(4)
    assert model.cross_batch
    assert {p.items_per_sample for p in unet.attn_processors.values() if hasattr(p, "items_per_sample")} == {4}


def test_terminal_input_zero_makes_the_terminal_prediction_deterministic():
    """schedule.terminal_input: zero: at t = T-1 the UNet reads 0 instead of x_t, at every other t
    it reads x_t; single-step results then no longer depend on the noise draw."""
    reference, model = _model(), _model(terminal_timestep=999)  # same seed, same weights
    cond, ids, ehs, n = _inputs(2, 4)
    x, y = torch.randn(2, n, LATENT, 8, 8, generator=torch.Generator().manual_seed(1))
    t = torch.tensor([999] * 4 + [500] * 4)  # one timestep per sample, shared by its views
    with torch.no_grad():
        plain = reference(x, cond, t, ids, ehs)
        zeroed_by_hand = reference(torch.cat([torch.zeros_like(x[:4]), x[4:]]), cond, t, ids, ehs)
        vx, vy = model(x, cond, t, ids, ehs), model(y, cond, t, ids, ehs)
    torch.testing.assert_close(vx, zeroed_by_hand, atol=0, rtol=0)  # exactly "zero the terminal items"
    assert not torch.equal(vx, plain)
    torch.testing.assert_close(vx[:4], vy[:4], atol=0, rtol=0)  # the terminal sample ignores x_t
    assert not torch.equal(vx[4:], vy[4:])  # t = 500 still reads its noisy latent

    zero_snr = make_train_scheduler(rescale_zero_snr=True, timestep_spacing="trailing").config
    run = lambda seed, **kw: sample(
        model,
        cond,
        ids,
        ehs,
        items_per_sample=4,
        scheduler_config=zero_snr,
        generator=torch.Generator().manual_seed(seed),
        **kw,
    )
    single = run(0, mode="single_step")
    torch.testing.assert_close(run(1, mode="single_step"), single, atol=0, rtol=0)
    with pytest.warns(UserWarning, match="repeats one prediction"):
        torch.testing.assert_close(run(0, mode="single_step", ensemble=3), single, atol=1e-6, rtol=0)
    torch.testing.assert_close(run(1, steps=1), single, atol=1e-5, rtol=0)  # trailing 1-step DDIM = single step
    assert not torch.equal(run(0, steps=3), run(1, steps=3))  # later DDIM steps still read x_t


def test_terminal_input_zero_needs_zero_snr():
    from pydantic import ValidationError

    from pilight.params import ScheduleParams

    assert ScheduleParams(rescale_zero_snr=True, terminal_input="zero").terminal_input == "zero"
    with pytest.raises(ValidationError, match="terminal_input 'zero' needs schedule.rescale_zero_snr"):
        ScheduleParams(rescale_zero_snr=False, terminal_input="zero")


class _OracleV(torch.nn.Module):
    """A 'perfect' model for one known x0: from (x_t, t) it returns the exact v that the
    forward process would have produced, v = sqrt(a) eps - sqrt(1-a) x0, eps recovered from x_t.
    At a zero-SNR terminal step (a = 0) x_t is the noise itself, so eps = x_t there too."""

    latent_channels, items_per_sample = LATENT, 1

    def __init__(self, x0: torch.Tensor, alphas_cumprod: torch.Tensor):
        super().__init__()
        self.x0, self.alphas = x0, alphas_cumprod.double()
        self.anchor = torch.nn.Parameter(torch.zeros(()))  # sample() reads the dtype from parameters

    def set_items_per_sample(self, views):
        self.items_per_sample = views

    terminal_zero = False  # read 0 instead of x_t at t = T-1 (schedule.terminal_input: zero)

    def forward(self, x_t, cond, t, ids, ehs):
        if self.terminal_zero:
            x_t = torch.where((t == len(self.alphas) - 1).view(-1, 1, 1, 1), torch.zeros_like(x_t), x_t)
        a = self.alphas[t.long()].view(-1, 1, 1, 1)
        x0 = self.x0.repeat(x_t.shape[0] // self.x0.shape[0], 1, 1, 1).double()
        eps = (x_t.double() - a.sqrt() * x0) / (1 - a).sqrt()
        return (a.sqrt() * eps - (1 - a).sqrt() * x0).float()


@pytest.mark.parametrize(
    "zero_snr,spacing,terminal_zero",
    [(True, "trailing", False), (True, "leading", False), (False, "trailing", False), (True, "trailing", True)],
)
@pytest.mark.parametrize("steps", [1, 4, 25])
def test_ddim_with_the_exact_v_recovers_x0(zero_snr, spacing, terminal_zero, steps):
    # The loop itself (scheduler config, timestep order, v -> x0 inside DDIMScheduler) must be
    # lossless: if an oracle's exact v did not give back x0, multi-step results would be wrong
    # for reasons no amount of training fixes (wrong prediction type, alpha at the final step,
    # a zero-SNR step mishandled, ensemble members misaligned).
    config = make_train_scheduler(rescale_zero_snr=zero_snr, timestep_spacing=spacing).config
    x0 = torch.randn(2 * DOMAINS, LATENT, 8, 8, generator=torch.Generator().manual_seed(3))
    scheduler = make_train_scheduler(rescale_zero_snr=zero_snr)
    oracle = _OracleV(x0, scheduler.alphas_cumprod)
    oracle.terminal_zero = terminal_zero  # the sampler steps from the real x_T, so this stays exact
    cond, ids, ehs, _ = _inputs(2, DOMAINS)
    out = sample(
        oracle,
        cond,
        ids,
        ehs,
        items_per_sample=DOMAINS,
        steps=steps,
        timestep_spacing=spacing,
        generator=torch.Generator().manual_seed(0),
        scheduler_config=config,
        ensemble=2,
    )
    torch.testing.assert_close(out, x0, atol=1e-4, rtol=0)
    if zero_snr:
        one = sample(
            oracle,
            cond,
            ids,
            ehs,
            items_per_sample=DOMAINS,
            mode="single_step",
            scheduler_config=config,
            generator=torch.Generator().manual_seed(0),
        )
        torch.testing.assert_close(one, x0, atol=1e-4, rtol=0)
