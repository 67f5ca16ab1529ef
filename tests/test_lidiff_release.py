"""LiDiff at ``size: paper`` computes what its release computes: weights from a file in the release's layout
(``diff_net.ckpt``: ``partial_enc.*`` and ``model.*``, MinkowskiEngine kernels), a few hundred points, and the
predicted noise against an independent float64 reference of ``MinkGlobalEnc`` + ``MinkUNetDiff`` built from the
release's facts: 5 cm voxels of round(p / 0.05) averaging their points (UNWEIGHTED_AVERAGE), MinkowskiEngine's
convolutions by dictionary lookups over coordinates in base units at each tensor stride (kernel offsets with the
first axis fastest; a stride-2 kernel-2 convolution to floor(c / 2s) 2s, its transpose back onto the encoder's
sites), the conditioning of every level by the nearest scan feature (``match_part_to_full``) and the timestep, ``ME.cat``
and ``slice``. The scans are placed so that no voxel is equidistant from two scan features (the release's KeOps
argmin and a k-d tree may break such ties differently)."""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F

from test_lidiff_paper import lidiff, me_offset, release_layout

Coord = tuple[int, int, int, int]


class NaiveME:
    """MinkowskiEngine's layers on {coordinate: row} dictionaries, from the release's state dict ``r``."""

    def __init__(self, r: dict[str, torch.Tensor]) -> None:
        self.r = r

    def conv(self, name: str, feats: torch.Tensor, coords: list[Coord], ts: int, ks: int, stride: int) \
            -> tuple[torch.Tensor, list[Coord]]:
        w = self.r[name + ".kernel"]
        w = w[None] if w.dim() == 2 else w
        where = {c: i for i, c in enumerate(coords)}
        if stride == 1:
            outs = coords
        else:
            outs = sorted({(c[0],) + tuple(math.floor(v / (stride * ts)) * stride * ts for v in c[1:])
                           for c in coords})
        out = feats.new_zeros(len(outs), w.shape[2])
        for n, o in enumerate(outs):
            for k in range(w.shape[0]):
                off = me_offset(k, (ks, ks, ks))
                src = (o[0],) + tuple(o[a + 1] + off[a] * ts for a in range(3))
                if src in where:
                    out[n] = out[n] + feats[where[src]] @ w[k]
        return out, outs

    def conv_transpose(self, name: str, feats: torch.Tensor, coords: list[Coord], fine: list[Coord],
                       ts_fine: int) -> torch.Tensor:
        """Kernel 2, stride 2, back onto the existing ``fine`` sites: each takes its coarse parent with the kernel
        index of its offset from it."""
        w = self.r[name + ".kernel"]
        where = {c: i for i, c in enumerate(coords)}
        out = feats.new_zeros(len(fine), w.shape[2])
        for n, c in enumerate(fine):
            parent = (c[0],) + tuple(math.floor(v / (2 * ts_fine)) * 2 * ts_fine for v in c[1:])
            off = [(c[a + 1] - parent[a + 1]) // ts_fine for a in range(3)]
            if parent in where:
                out[n] = feats[where[parent]] @ w[off[0] + 2 * off[1] + 4 * off[2]]
        return out

    def bn(self, name: str, x: torch.Tensor) -> torch.Tensor:
        r = self.r
        return (x - r[name + ".bn.running_mean"]) / torch.sqrt(r[name + ".bn.running_var"] + 1e-5) * \
            r[name + ".bn.weight"] + r[name + ".bn.bias"]

    def residual(self, p: str, x: torch.Tensor, coords: list[Coord], ts: int) -> torch.Tensor:
        h = torch.relu(self.bn(p + "net.1", self.conv(p + "net.0", x, coords, ts, 3, 1)[0]))
        h = self.bn(p + "net.4", self.conv(p + "net.3", h, coords, ts, 3, 1)[0])
        skip = x if p + "downsample.0.kernel" not in self.r else \
            self.bn(p + "downsample.1", self.conv(p + "downsample.0", x, coords, ts, 1, 1)[0])
        return torch.relu(h + skip)

    def stem(self, p: str, x: torch.Tensor, coords: list[Coord]) -> torch.Tensor:
        x = torch.relu(self.bn(p + "stem.1", self.conv(p + "stem.0", x, coords, 1, 3, 1)[0]))
        return torch.relu(self.bn(p + "stem.4", self.conv(p + "stem.3", x, coords, 1, 3, 1)[0]))

    def stage(self, p: str, x: torch.Tensor, coords: list[Coord], ts: int) -> tuple[torch.Tensor, list[Coord]]:
        x, coords = self.conv(p + "0.net.0", x, coords, ts, 2, 2)
        x = torch.relu(self.bn(p + "0.net.1", x))
        for i in (1, 2):
            x = self.residual(f"{p}{i}.", x, coords, 2 * ts)
        return x, coords

    def mlp(self, p: str, x: torch.Tensor) -> torch.Tensor:
        h = F.leaky_relu(x @ self.r[p + "0.weight"].t() + self.r[p + "0.bias"], 0.1)
        return h @ self.r[p + "2.weight"].t() + self.r[p + "2.bias"]


def voxels(points: torch.Tensor) -> tuple[torch.Tensor, list[Coord], list[int]]:
    """(the voxels' mean points, their coordinates round(p / 0.05) with the batch first, each point's voxel row)."""
    cells = [(b, *(int(v) for v in torch.round(p / 0.05).tolist())) for b in range(len(points)) for p in points[b]]
    coords = sorted(set(cells))
    row = {c: i for i, c in enumerate(coords)}
    total = torch.zeros(len(coords), 3, dtype=torch.float64)
    count = torch.zeros(len(coords), dtype=torch.float64)
    for c, p in zip(cells, points.reshape(-1, 3)):
        total[row[c]] += p
        count[row[c]] += 1
    return total / count[:, None], coords, [row[c] for c in cells]


def reference(r: dict[str, torch.Tensor], x_t: torch.Tensor, t: torch.Tensor, scan: torch.Tensor) -> torch.Tensor:
    me = NaiveME({k: v.double() for k, v in r.items()})
    # the scan encoder: stem, four stages to stride 16
    part, pc, _ = voxels(scan)
    part = me.stem("partial_enc.", part, pc)
    for level in range(4):
        part, pc = me.stage(f"partial_enc.stage{level + 1}.", part, pc, 2 ** level)
    # the timestep embedding, as released (float32 products)
    half = 48
    freqs = torch.from_numpy(np.exp(np.arange(half) * -(math.log(10000) / (half - 1))))
    args = t[:, None] * freqs.float()[None]
    temb = torch.cat([torch.sin(args), torch.cos(args)], 1).double()

    def weights(level: int, x: torch.Tensor, coords: list[Coord]) -> torch.Tensor:
        names = ["stage1", "stage2", "stage3", "stage4", "up1", "up2", "up3", "up4"][level]
        matched = torch.stack([part[min((j for j in range(len(pc)) if pc[j][0] == c[0]),
                                        key=lambda j: sum((pc[j][a] - c[a]) ** 2 for a in (1, 2, 3)))]
                               for c in coords])
        p = me.mlp(f"model.latent_{names}.", matched)
        tt = me.mlp(f"model.{names}_temp.", temb)[[c[0] for c in coords]]
        return me.mlp(f"model.latemp_{names}.", torch.cat((tt, p) if names == "up1" else (p, tt), 1))

    feats, c0, rows = voxels(x_t)
    x0 = me.stem("model.", feats, c0)
    xs, cs = [x0], [c0]
    for level in range(4):
        x, c = me.stage(f"model.stage{level + 1}.", xs[-1] * weights(level, xs[-1], cs[-1]), cs[-1], 2 ** level)
        xs.append(x)
        cs.append(c)
    y, yc = xs[4], cs[4]
    for i in range(4):  # up1..up4: to stride 8, 4, 2, 1 onto the encoder's sites, then [y, skip]
        ts = 2 ** (3 - i)
        p = f"model.up{i + 1}."
        y = me.conv_transpose(p + "0.net.0", y * weights(4 + i, y, yc), yc, cs[3 - i], ts)
        y = torch.relu(me.bn(p + "0.net.1", y))
        yc = cs[3 - i]
        y = torch.cat([y, xs[3 - i]], 1)
        for j in (0, 1):
            y = me.residual(f"{p}1.{j}.", y, yc, ts)
    return me.mlp("model.last.", y[rows]).view(x_t.shape)


def clouds() -> tuple[torch.Tensor, torch.Tensor]:
    """Noisy points in a 0.45 m box per scene; scans: one 0.8 m cell beside it (scene 0), that cell and one 3.2 m
    away (scene 1): every voxel has one nearest scan feature."""
    g = torch.Generator().manual_seed(11)
    x_t = 0.02 + 0.45 * torch.rand(2, 180, 3, generator=g, dtype=torch.float64)
    scan = 0.05 + 0.7 * torch.rand(2, 60, 3, generator=g, dtype=torch.float64)
    scan[1, 30:, 0] += 3.2
    return x_t, scan


def test_a_released_checkpoint_gives_the_releases_noise(tmp_path) -> None:
    from distilkit.weights import load_weights

    model = lidiff(duplicate=4)
    g = torch.Generator().manual_seed(3)
    state = {}
    for key, value in model.state_dict().items():  # random weights of a sensible scale and batch-norm statistics
        if key.endswith("num_batches_tracked"):
            state[key] = value
        elif key.endswith("running_var"):
            state[key] = 0.5 + torch.rand(value.shape, generator=g)
        elif key.endswith(("running_mean", "bias")):
            state[key] = 0.2 * torch.randn(value.shape, generator=g)
        elif value.dim() == 1:
            state[key] = 1 + 0.2 * torch.randn(value.shape, generator=g)
        else:
            state[key] = torch.randn(value.shape, generator=g) * (1.5 / value[0].numel()) ** 0.5
    release = release_layout(state, {"partial_enc.": 0, "model.": 0})
    torch.save({"state_dict": release, "epoch": 9}, tmp_path / "diff_net.ckpt")
    assert load_weights(model, type(model).read_weights(str(tmp_path / "diff_net.ckpt")), True, "diff_net") == []
    model = model.double().eval()
    x_t, scan = clouds()
    t = torch.tensor([17, 640])
    with torch.no_grad():
        got = model.net(x_t, t, scan)
        want = reference(release, x_t, t, scan)
    assert got.shape == (2, 180, 3) and want.abs().max() > 0.1
    assert torch.allclose(got, want, rtol=1e-9, atol=1e-9 * float(want.abs().max()))
