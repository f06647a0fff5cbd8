"""The map networks: the paper's U-Net with a global skip connection (§3.3), its
ablation variants, and the input encoding that lets one set of weights take any
subset of the rig's lights.

The U-Net (preset ``paper``): one conv to ``base`` = 64 channels; ``depth`` = 7
down blocks, each three 3×3 convs with LeakyReLU, the first with stride 2 adding
``growth`` = 32 channels; a bottleneck conv; 7 up blocks, each a stride-2
transposed conv back to the encoder level's channel count, concatenation with
that level's encoder features, then two 3×3 convs; and at every level the
**global skip connection** (Eq. 5): global average pooling of E_i → FC → SELU →
FC → broadcast and add to D_i. Heads: G_d and G_s plain (a conv), G_g a conv and
sigmoid (glossiness; roughness = 1 − g), G_n a conv and tanh normalised to unit
length and built without global skips.

Variants behind the same interface (``variant``): ``four`` (the paper: four
independent networks), ``one_encoder`` (one shared encoder, four decoders),
``global_track`` (Deschaintre et al. 2018's global feature track instead of the
global skip), ``no_global_skip``.

Inputs (:func:`network_input`): for a rig of L lights, L RGB slots (each photo
divided by the irradiance a flat surface receives there from its light, then
log-encoded; 0 for an absent light), L presence planes (1 present, 0 absent) and
two planes of the pixel's position in the sample field (x, y in [−1, 1]), so a
network knows which photos it has and where in the dome a crop lies: 4L + 2
channels. (The paper feeds the 3N photo channels as they are; dividing out the
rig's known falloff and cosines is ours, to make training practical on a CPU.)

With ``diffuse_from_photos`` (the ``cpu`` preset), G_d's output is added to the
albedo the photos show (:func:`photo_albedo`), so it learns a correction (highlights,
shadows, few lights) instead of reproducing every texture detail through the
U-Net: ours, for training on a CPU budget; the ``paper`` preset keeps G_d plain.
``photo_statistic`` says which order statistic of the photos that albedo is: the
``cpu`` preset takes the lower third, as the trivial baseline does
(:func:`matscan.render.flat_albedo`); networks trained before the field existed
used the median and load with it (:func:`matscan.train.net_config_of`).

Sizes that are not a multiple of 2^depth are padded (reflect) up to one and the
outputs cropped back (:meth:`MapNets.forward`).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from matscan.errors import MatscanError
from matscan.render import flat_irradiance, surface_points
from matscan.rig import LightSet, Rig

MAPS = ("diffuse", "specular", "roughness", "normal")
OUT_CHANNELS = {"diffuse": 3, "specular": 3, "roughness": 1, "normal": 3}
VARIANTS = ("four", "one_encoder", "global_track", "no_global_skip")
#: Scale of the log encoding of radiance: log1p(x · LOG_SCALE) / log1p(LOG_SCALE).
LOG_SCALE = 100.0
#: Smallest irradiance a photo is divided by (:func:`network_input`).
IRRADIANCE_FLOOR = 0.05


#: Which order statistic of photo ÷ flat irradiance over the n present lights is the
#: albedo the photos show (:func:`photo_albedo`): sorted index ⌊(n − 1)/2⌋ (the lower
#: median, as torch.nanmedian) or ⌊(n − 1)/3⌋ (the lower third, which drops a highlight
#: seen in two of three photos: Table 4's 3-light subset has two lights beside the camera).
PHOTO_STATISTICS = {"median": 2, "lower_third": 3}


@dataclass(frozen=True)
class NetConfig:
    """Shape of one U-Net."""

    base: int = 64
    growth: int = 32
    depth: int = 7
    global_dim: int = 0  # width of the global FC layers; 0: the level's channel count
    diffuse_from_photos: bool = False  # G_d predicts a correction to the photos' albedo (see photo_albedo)
    photo_statistic: str = "median"  # that albedo's order statistic over the present lights: see PHOTO_STATISTICS

    def __post_init__(self) -> None:
        if self.photo_statistic not in PHOTO_STATISTICS:
            raise MatscanError(f"photo_statistic: {self.photo_statistic!r} is not one of {', '.join(PHOTO_STATISTICS)}")

    def channels(self) -> list[int]:
        return [self.base + self.growth * i for i in range(self.depth + 1)]


PRESETS: dict[str, NetConfig] = {
    "paper": NetConfig(base=64, growth=32, depth=7),
    # 1.16 M parameters a network; a training step (batch 4, 128²) takes about 0.65 s here
    "cpu": NetConfig(base=16, growth=16, depth=5, diffuse_from_photos=True, photo_statistic="lower_third"),
    "tiny": NetConfig(base=8, growth=8, depth=3),  # for tests
}


def preset(name: str) -> NetConfig:
    """A named network shape (``paper``, ``cpu``, ``tiny``)."""
    try:
        return PRESETS[name]
    except KeyError:
        raise MatscanError(f"preset: {name!r} is not one of {', '.join(PRESETS)}") from None


def encode_inputs(
    photos: Tensor, present: Tensor, offset: Tensor | None = None, full_size: Tensor | None = None
) -> Tensor:
    """Network input from photos in rig-light slots.

    Args:
        photos: (B, L, 3, H, W) linear radiance, 0 for absent lights.
        present: (B, L) 1 for photographed lights.
        offset, full_size: (B, 2) crop position (rows, cols) in, and size of, the
            full map covering the rig's field; None for a full-field input.

    Returns:
        (B, 4L + 2, H, W): log-encoded photos, presence planes, field x and y in [−1, 1].
    """
    b, n, c, h, w = photos.shape
    like = {"dtype": photos.dtype, "device": photos.device}  # offset and full_size may be on the CPU
    logs = torch.log1p(photos.clamp_min(0) * LOG_SCALE) / math.log1p(LOG_SCALE)
    logs = logs * present.view(b, n, 1, 1, 1)
    planes = present.view(b, n, 1, 1).expand(b, n, h, w)
    offset = torch.zeros(b, 2, **like) if offset is None else offset.to(**like)
    full_size = torch.tensor([[h, w]] * b, **like) if full_size is None else full_size.to(**like)
    rows = torch.arange(h, **like).view(1, h, 1) + offset[:, 0].view(b, 1, 1) + 0.5
    cols = torch.arange(w, **like).view(1, 1, w) + offset[:, 1].view(b, 1, 1) + 0.5
    x = (cols / full_size[:, 1].view(b, 1, 1)) * 2 - 1
    y = 1 - (rows / full_size[:, 0].view(b, 1, 1)) * 2
    coords = torch.stack([x.expand(b, h, w), y.expand(b, h, w)], dim=1)
    return torch.cat([logs.reshape(b, n * c, h, w), planes.to(photos.dtype), coords], dim=1)


def network_input(
    photos: Tensor,
    present: Tensor,
    offset: Tensor | None,
    full_size: Tensor | None,
    rig: Rig,
    field_mm: tuple[float, float] | None = None,
) -> Tensor:
    """:func:`encode_inputs` of photos divided by the irradiance a flat surface gets
    from each light at each pixel (:func:`matscan.render.flat_irradiance`).

    A Lambertian pixel of albedo ρ then reads ρ under every light, wherever it lies
    in the dome: the networks need not learn the rig's falloff and cosines, and
    highlights stand out as departures from that. Computed on ``photos``' device;
    ``offset`` and ``full_size`` are best left on the CPU (they are read as numbers).
    """
    b, n, _, h, w = photos.shape
    if offset is None:
        offset = torch.zeros(b, 2, dtype=torch.long)
    if full_size is None:
        full_size = torch.tensor([[h, w]] * b)
    lights = lights_to(rig.light_set(), photos.device)
    field = field_mm if field_mm is not None else rig.field_mm
    places = zip(offset.tolist(), full_size.tolist(), strict=True)
    irr = torch.stack(
        [
            flat_irradiance(lights, surface_points(field, (h, w), tuple(o), tuple(f)).to(photos.device))
            for o, f in places
        ]
    )
    return encode_inputs(photos / irr.clamp_min(IRRADIANCE_FLOOR), present, offset, full_size)


def lights_to(lights: LightSet, device: torch.device | str) -> LightSet:
    """The same lights with their tensors on ``device``."""
    return lights.to(device)


def photo_albedo(x: Tensor, n_lights: int, statistic: str = "median") -> Tensor:
    """The albedo the photos show, decoded from a :func:`network_input`.

    Args:
        x: (B, 4L + 2, H, W) network input of L = ``n_lights`` slots.
        statistic: a key of :data:`PHOTO_STATISTICS`: per pixel and channel, the
            order statistic of photo ÷ flat irradiance over the n present lights at
            sorted index ⌊(n − 1)/2⌋ (``median``) or ⌊(n − 1)/3⌋ (``lower_third``).

    Returns:
        (B, 3, H, W) linear albedo in [0, 1]; 0 where no light is present. Highlights
        only add light and fall out of a low order statistic; with few lights the
        network corrects what is left.
    """
    b, _, h, w = x.shape
    logs = x[:, : 3 * n_lights].reshape(b, n_lights, 3, h, w)
    present = x[:, 3 * n_lights : 4 * n_lights, :1, :1].reshape(b, n_lights, 1, 1, 1) > 0.5
    ratio = torch.expm1(logs * math.log1p(LOG_SCALE)) / LOG_SCALE
    ratio = torch.where(present, ratio, torch.full_like(ratio, math.inf))  # absent lights sort last
    count = present.reshape(b, n_lights).sum(dim=1)  # (B,)
    k = ((count - 1).clamp_min(0) // PHOTO_STATISTICS[statistic]).view(b, 1, 1, 1, 1).expand(b, 1, 3, h, w)
    value = ratio.sort(dim=1).values.gather(1, k)[:, 0]  # (B, 3, H, W)
    return torch.where(count.view(b, 1, 1, 1) > 0, value, torch.zeros_like(value)).clamp(0, 1)


def input_channels(n_lights: int) -> int:
    return 4 * n_lights + 2


def _conv(cin: int, cout: int, stride: int = 1) -> nn.Conv2d:
    return nn.Conv2d(cin, cout, 3, stride=stride, padding=1)


class GlobalSkip(nn.Module):
    """Eq. 5: GAP(E_i) → FC → SELU → FC, broadcast-added to D_i."""

    def __init__(self, channels: int, hidden: int) -> None:
        super().__init__()
        self.fc1 = nn.Linear(channels, hidden)
        self.fc2 = nn.Linear(hidden, channels)

    def forward(self, decoded: Tensor, pooled: Tensor) -> Tensor:
        g = self.fc2(F.selu(self.fc1(pooled)))  # (B, C)
        return decoded + g[:, :, None, None]


class GlobalTrack(nn.Module):
    """Deschaintre et al. 2018's global feature track, one stage: the running global
    vector takes the mean of this level's features, and is added back to them."""

    def __init__(self, channels: int, dim: int) -> None:
        super().__init__()
        self.mix = nn.Linear(dim + channels, dim)
        self.out = nn.Linear(dim, channels)

    def forward(self, x: Tensor, g: Tensor) -> tuple[Tensor, Tensor]:
        g = F.selu(self.mix(torch.cat([g, x.mean(dim=(2, 3))], dim=1)))
        return x + self.out(g)[:, :, None, None], g


class Encoder(nn.Module):
    def __init__(self, in_channels: int, cfg: NetConfig, track: bool = False) -> None:
        super().__init__()
        ch = cfg.channels()
        self.stem = _conv(in_channels, ch[0])
        self.blocks = nn.ModuleList(
            nn.ModuleList([_conv(ch[i], ch[i + 1], 2), _conv(ch[i + 1], ch[i + 1]), _conv(ch[i + 1], ch[i + 1])])
            for i in range(cfg.depth)
        )
        self.bottleneck = _conv(ch[-1], ch[-1])
        self.track_dim = cfg.global_dim or ch[-1]
        self.tracks = nn.ModuleList(GlobalTrack(c, self.track_dim) for c in ch[1:]) if track else None

    def forward(self, x: Tensor) -> tuple[list[Tensor], Tensor | None]:
        """Encoder features E_0 … E_depth (the last after the bottleneck), and the
        global track's vector when there is one."""
        feats = [F.leaky_relu(self.stem(x), 0.2)]
        g = x.new_zeros(x.shape[0], self.track_dim) if self.tracks is not None else None
        for i, block in enumerate(self.blocks):
            h = feats[-1]
            for conv in block:
                h = F.leaky_relu(conv(h), 0.2)
            if self.tracks is not None:
                h, g = self.tracks[i](h, g)
            feats.append(h)
        feats[-1] = F.leaky_relu(self.bottleneck(feats[-1]), 0.2)
        return feats, g


class Decoder(nn.Module):
    def __init__(self, out_channels: int, cfg: NetConfig, skip: str, head: str) -> None:
        super().__init__()
        ch = cfg.channels()
        self.ups = nn.ModuleList(nn.ConvTranspose2d(ch[i + 1], ch[i], 2, stride=2) for i in range(cfg.depth))
        self.convs = nn.ModuleList(
            nn.ModuleList([_conv(2 * ch[i], ch[i]), _conv(ch[i], ch[i])]) for i in range(cfg.depth)
        )
        hidden = cfg.global_dim
        self.skip = skip
        if skip == "fc":
            self.globals = nn.ModuleList(GlobalSkip(ch[i], hidden or ch[i]) for i in range(cfg.depth + 1))
        elif skip == "track":
            dim = cfg.global_dim or ch[-1]
            self.tracks = nn.ModuleList(GlobalTrack(ch[i], dim) for i in range(cfg.depth))
        self.head = _conv(ch[0], out_channels)
        self.head_kind = head

    def forward(self, feats: list[Tensor], g: Tensor | None = None, pooled: list[Tensor] | None = None) -> Tensor:
        """``pooled``: per-level global averages of the encoder features to use instead
        of this input's (for tiled inference, computed over the whole image)."""
        if self.skip == "fc" and pooled is None:
            pooled = [f.mean(dim=(2, 3)) for f in feats]
        d = feats[-1]
        if self.skip == "fc":
            d = self.globals[-1](d, pooled[-1])
        for i in reversed(range(len(self.ups))):
            d = F.leaky_relu(self.ups[i](d), 0.2)  # (B, ch[i], 2h, 2w)
            d = torch.cat([d, feats[i]], dim=1)
            for conv in self.convs[i]:
                d = F.leaky_relu(conv(d), 0.2)
            if self.skip == "fc":
                d = self.globals[i](d, pooled[i])
            elif self.skip == "track":
                d, g = self.tracks[i](d, g)
        out = self.head(d)
        if self.head_kind == "sigmoid":
            return torch.sigmoid(out)
        if self.head_kind == "unit":
            return F.normalize(torch.tanh(out), dim=1, eps=1e-6)
        return out


HEADS = {"diffuse": "plain", "specular": "plain", "roughness": "sigmoid", "normal": "unit"}


def _skip_kind(name: str, variant: str) -> str:
    if name == "normal" or variant == "no_global_skip":
        return "none"  # the paper's G_n has no global skips
    return "track" if variant == "global_track" else "fc"


class UNet(nn.Module):
    """One map network: encoder + decoder (see module doc)."""

    def __init__(self, in_channels: int, name: str, cfg: NetConfig, variant: str = "four") -> None:
        super().__init__()
        skip = _skip_kind(name, variant)
        self.encoder = Encoder(in_channels, cfg, track=skip == "track")
        self.decoder = Decoder(OUT_CHANNELS[name], cfg, skip, HEADS[name])

    def forward(self, x: Tensor, pooled: list[Tensor] | None = None) -> Tensor:
        feats, g = self.encoder(x)
        return self.decoder(feats, g, pooled)


class MapNets(nn.Module):
    """The four map networks (or a variant) behind one interface.

    ``forward`` takes the encoded input (:func:`encode_inputs`) and returns maps in
    design.md conventions: diffuse and specular clamped to [0, 1] outside
    training, roughness = 1 − glossiness, unit normals.
    """

    def __init__(self, n_lights: int, cfg: NetConfig, variant: str = "four", maps: tuple[str, ...] = MAPS) -> None:
        super().__init__()
        if variant not in VARIANTS:
            raise MatscanError(f"variant: {variant!r} is not one of {', '.join(VARIANTS)}")
        for m in maps:
            if m not in MAPS:
                raise MatscanError(f"maps: {m!r} is not one of {', '.join(MAPS)}")
        self.cfg, self.variant, self.maps, self.n_lights = cfg, variant, tuple(maps), n_lights
        cin = input_channels(n_lights)
        if variant == "one_encoder":
            self.shared = Encoder(cin, cfg)
            self.decoders = nn.ModuleDict(
                {m: Decoder(OUT_CHANNELS[m], cfg, _skip_kind(m, variant), HEADS[m]) for m in maps}
            )
        else:
            self.nets = nn.ModuleDict({m: UNet(cin, m, cfg, variant) for m in maps})

    @property
    def multiple(self) -> int:
        return 2**self.cfg.depth

    def _pad(self, x: Tensor) -> Tensor:
        h, w = x.shape[-2:]
        m = self.multiple
        ph, pw = (-h) % m, (-w) % m
        if ph or pw:  # reflect-pad to a multiple of 2^depth; outputs are cropped back
            mode = "reflect" if ph < h and pw < w else "replicate"
            x = F.pad(x, (0, pw, 0, ph), mode=mode)
        return x

    @torch.no_grad()
    def encoder_sums(self, x: Tensor) -> dict[str, list[Tensor]]:
        """Per network, per level: the sum over pixels of the encoder features, (B, C).

        Summed over tiles and divided by each level's pixel count, they give the
        whole image's global averages that the global skips need (:meth:`forward`
        ``pooled``)."""
        x = self._pad(x)
        if self.variant == "one_encoder":
            feats, _ = self.shared(x)
            sums = [f.sum(dim=(2, 3)) for f in feats]
            return {name: sums for name in self.decoders}
        return {name: [f.sum(dim=(2, 3)) for f in net.encoder(x)[0]] for name, net in self.nets.items()}

    def forward(self, x: Tensor, pooled: dict[str, list[Tensor]] | None = None) -> dict[str, Tensor]:
        """Maps from the encoded input. ``pooled`` (per network, per level (B, C)) replaces
        the input's own global averages: tiled inference passes the whole image's."""
        h, w = x.shape[-2:]
        x = self._pad(x)
        pooled = pooled or {}
        if self.variant == "one_encoder":
            feats, g = self.shared(x)
            raw = {name: dec(feats, g, pooled.get(name)) for name, dec in self.decoders.items()}
        else:
            raw = {name: net(x, pooled.get(name)) for name, net in self.nets.items()}
        out = {}
        for name, t in raw.items():
            t = t[..., :h, :w]
            if name == "diffuse" and self.cfg.diffuse_from_photos:
                t = t + photo_albedo(x[..., :h, :w], self.n_lights, self.cfg.photo_statistic)
            if name == "roughness":
                t = 1 - t  # G_g predicts glossiness
            elif name in ("diffuse", "specular") and not self.training:
                t = t.clamp(0, 1)
            out[name] = t
        return out

    def describe(self) -> dict:
        return {
            "config": asdict(self.cfg),
            "variant": self.variant,
            "maps": list(self.maps),
            "n_lights": self.n_lights,
            "parameters": sum(p.numel() for p in self.parameters()),
        }
