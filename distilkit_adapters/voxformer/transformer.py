"""VoxFormer's transformer parts as released (mmcv's bricks as its configs build them; names kept, so that a
VoxFormer checkpoint loads):

* :class:`FFN` — ``layers.0.0`` Linear(C, F), ReLU, Dropout, ``layers.1`` Linear(F, C), Dropout, plus its input. The
  configs give the FFN 1024 channels and a dropout of 0, but the layer's ``feedforward_channels=256`` and
  ``ffn_dropout=0.1`` replace them (mmcv's deprecated arguments win): F = 2C = 256, dropout 0.1.
* :class:`EncoderLayer` — ``attentions.0`` (cross or self), ``norms.0``, ``ffns.0``, ``norms.1``:
  ``operation_order`` (attn, norm, ffn, norm); the attention and the FFN add their own residuals.
* :class:`LearnedPositionalEncoding` — mmcv's: ``row_embed`` and ``col_embed`` (512 x C/2 each); the position of
  cell (row, column) of the 512 x 512 plane is [col_embed[column], row_embed[row]], and query n takes the plane's
  cell n (the queries' flat order folded to the plane, as the release's ``bev_pos`` is).
* :class:`PerceptionTransformer` — ``level_embeds`` (4 x C) and ``cams_embeds`` (images x C), added to the image
  features before the cross-attention reads them (the first level's only: the FPN gives one), and ``encoder.layers``.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from distilkit_adapters.voxformer.deformable import DeformCrossAttention, DeformSelfAttention


class FFN(nn.Module):
    def __init__(self, embed_dims: int, channels: int, dropout: float = 0.1) -> None:
        super().__init__()
        self.layers = nn.Sequential(nn.Sequential(nn.Linear(embed_dims, channels), nn.ReLU(inplace=True),
                                                  nn.Dropout(dropout)),
                                    nn.Linear(channels, embed_dims), nn.Dropout(dropout))

    def forward(self, x: Tensor) -> Tensor:
        return x + self.layers(x)


class EncoderLayer(nn.Module):
    """(attention, norm, FFN, norm) with the release's names."""

    def __init__(self, attention: nn.Module, embed_dims: int, ffn_channels: int, dropout: float = 0.1) -> None:
        super().__init__()
        self.attentions = nn.ModuleList([attention])
        self.ffns = nn.ModuleList([FFN(embed_dims, ffn_channels, dropout)])
        self.norms = nn.ModuleList([nn.LayerNorm(embed_dims), nn.LayerNorm(embed_dims)])

    def finish(self, x: Tensor) -> Tensor:
        """The layer after its attention: norm, FFN, norm."""
        return self.norms[1](self.ffns[0](self.norms[0](x)))


class LearnedPositionalEncoding(nn.Module):
    def __init__(self, num_feats: int, row_num_embed: int = 512, col_num_embed: int = 512) -> None:
        super().__init__()
        self.row_embed = nn.Embedding(row_num_embed, num_feats)
        self.col_embed = nn.Embedding(col_num_embed, num_feats)
        nn.init.uniform_(self.row_embed.weight)
        nn.init.uniform_(self.col_embed.weight)

    def forward(self, n: int, rows: int = 512, columns: int = 512) -> Tensor:
        """(n, 2 num_feats) positions of the first ``n`` cells of a ``rows`` x ``columns`` plane, row by row."""
        if n > rows * columns or rows > len(self.row_embed.weight) or columns > len(self.col_embed.weight):
            raise ValueError(f"{n} queries do not fit the {len(self.row_embed.weight)} x "
                             f"{len(self.col_embed.weight)} positional encoding")
        cell = torch.arange(n, device=self.row_embed.weight.device)
        return torch.cat([self.col_embed(cell % columns), self.row_embed(cell // columns)], -1)


class Encoder(nn.Module):
    def __init__(self, layers: list[EncoderLayer]) -> None:
        super().__init__()
        self.layers = nn.ModuleList(layers)


class PerceptionTransformer(nn.Module):
    """The release's transformer: its embeddings of the image features and its encoder's layers."""

    def __init__(self, layers: list[EncoderLayer], embed_dims: int, num_cams: int, num_feature_levels: int = 4) -> None:
        super().__init__()
        self.level_embeds = nn.Parameter(torch.randn(num_feature_levels, embed_dims))
        self.cams_embeds = nn.Parameter(torch.randn(num_cams, embed_dims))
        self.encoder = Encoder(layers)

    def embed(self, features: Tensor) -> Tensor:
        """(T, C, h, w) image features -> (T, h * w, C) values: + each image's embedding + the first level's."""
        flat = features.flatten(2).transpose(1, 2)
        return flat + self.cams_embeds[: len(features), None] + self.level_embeds[None, 0:1]


def cross_layer(embed_dims: int, heads: int, points: int, ffn_channels: int) -> EncoderLayer:
    return EncoderLayer(DeformCrossAttention(embed_dims, heads, points), embed_dims, ffn_channels)


def self_layer(embed_dims: int, heads: int, points: int, ffn_channels: int, space: str) -> EncoderLayer:
    return EncoderLayer(DeformSelfAttention(embed_dims, heads, points, space), embed_dims, ffn_channels)


__all__ = ["FFN", "EncoderLayer", "LearnedPositionalEncoding", "PerceptionTransformer", "cross_layer", "self_layer"]
