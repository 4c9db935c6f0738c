"""LaneFormer head (Han et al., "Laneformer: Object-aware Row-Column Transformers for Lane Detection", AAAI 2022).

A DETR-style lane detector on the backbone's last (stride-32) feature map, projected to ``d_model`` channels.
There is no official code; what the paper says (arXiv 2203.09830: the abstract, Fig. 2 and its caption): the
encoder runs row attention on the row features Hr and column attention on the column features Hc, "added up with
the pixel-to-Bbox attention performed on Hf, Zb and Zr as memory input for decoder"; the abstract calls the pixel
part "deformable pixel-wise self-attention", the detected boxes' embeddings (Zb) added to its keys and their
ROI-aligned features (Zr) to its values. Here:

- the row branch. As the paper: the map is cut into its rows, each row flattened (its W positions x d
  channels) and projected by an fc layer to one d-dim *row token*; row tokens attend to each other (a row
  gathers the nearby rows, where the same lane continues) with 1-D sine encodings of the row index, in
  ``num_encoder_layers`` post-norm transformer layers. The column branch: the same over the columns.
  Each branch's output is broadcast back over the map (``row_column="lines"``, the default).
  ``row_column="axial"`` is the other reading (axial attention): every position is a token that attends to the
  positions of its own row (row branch) and of its own column (column branch).
- the pixel-wise branch (``pixel_attention``): every position of the map (Hf) a token attending to every other
  position, with DETR's 2-D sine encodings, ``num_encoder_layers`` layers: the paper's pixel-to-box attention
  without the boxes (no Zb keys, no Zr values), and dense instead of deformable (a stride-32 map has 250
  positions at 320x800, 40 at 128x320: dense attention is cheap there and needs no custom sampling op).
- the memory: the branches' outputs added, memory[i, j] = row[i] + col[j] + pixel[i, j].
- the decoder: ``num_queries`` learned lane queries (DETR: a zero target plus the learned query embedding as
  the positional part), each layer self-attention among the queries, cross-attention to the memory (keys
  carrying 2-D sine encodings), an FFN; a final LayerNorm shared by every layer's output. The transformer's
  matrices start Xavier-uniform as DETR's (facebookresearch/detr models/transformer.py, _reset_parameters).
- per query and decoder layer: 2 logits (background, lane) and the paper's lane: start y, end y (fractions
  of the height through a sigmoid stretched over [-Y_MARGIN, 1 + Y_MARGIN] of the height, so that a lane
  starting on the bottom row, the usual case, is a target the sigmoid reaches: 0.917, not its asymptote 1)
  and x at ``num_points`` fixed rows (fractions of the width, not bounded: a lane may leave the image). The
  loss (loss.py) runs on the last layer and, as DETR's auxiliary decoding losses, on every earlier one
  (``aux_loss``); those outputs are returned in training mode only.

Left out: the object-aware part (person and vehicle boxes from an external detector as extra keys and values,
in the encoder's pixel-to-box and the decoder's query-to-box attention) -- it needs a detector the project does
not have; both are additive to attention the network keeps, so the rest of the network is as described.

Training follows DETR (the paper builds on it; conf/model/laneformer.yaml): AdamW 1e-4, backbone 1e-5
(``model.lr_multipliers``), weight decay 1e-4, total gradient norm clipped at 0.1 (``model.gradient_clip_norm``).
A single large rate for the whole network with no clipping makes every query on every image predict the same
lane within ~10 steps (issue 32); tests/models/test_laneformer.py checks the recipe keeps them apart.
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from lanevil_train.models.head import LaneHead, lanes_with_scores
from lanevil_train.models.laneformer.loss import assemble_lane, encode_lanes, set_loss
from lanevil_train.models.rows import row_ys
from lanevil_train.rules import boolean, check_settings, integer, number, one_of

ROW_COLUMN_MODES = ("lines", "axial")
_PARTS = ("start_y", "end_y", "xs")
# start y and end y: sigmoid(z) stretched over [-Y_MARGIN, 1 + Y_MARGIN] of the height. A plain sigmoid would
# need z = +inf for the many lanes that start on the bottom row (y = 1): the L1 loss would push those logits
# up without end while the sigmoid's slope vanishes; with the margin that target is sigmoid(z) = 0.917, z = 2.4.
Y_MARGIN = 0.1


def y_from_logit(z: torch.Tensor) -> torch.Tensor:
    """A start / end y logit -> the y as a fraction of the height (in [-Y_MARGIN, 1 + Y_MARGIN])."""
    return torch.sigmoid(z) * (1 + 2 * Y_MARGIN) - Y_MARGIN


def y_to_logit(y: float) -> float:
    """The logit whose ``y_from_logit`` is y (a fraction of the height strictly inside the stretched range)."""
    s = (y + Y_MARGIN) / (1 + 2 * Y_MARGIN)
    return math.log(s / (1 - s))


def sine_encoding(n: int, dim: int) -> torch.Tensor:
    """(n, dim) 1-D sine / cosine encodings of the positions 0..n-1 (the transformer's, temperature 10000)."""
    pos = torch.arange(n, dtype=torch.float32)[:, None]
    freq = torch.exp(torch.arange(0, dim, 2, dtype=torch.float32) * (-math.log(10000.0) / dim))
    out = torch.zeros(n, dim)
    out[:, 0::2] = torch.sin(pos * freq)
    out[:, 1::2] = torch.cos(pos * freq)
    return out


class AttentionLayer(nn.Module):
    """A post-norm transformer layer (DETR's): attention of ``x`` (plus ``pos`` in queries and keys) over
    ``memory`` (plus ``mem_pos`` in keys; ``memory=None``: self-attention), then an FFN, residuals and LayerNorms."""

    def __init__(self, d_model: int, nhead: int, dim_feedforward: int, dropout: float) -> None:
        super().__init__()
        self.attn = nn.MultiheadAttention(d_model, nhead, dropout=dropout, batch_first=True)
        self.ffn = nn.Sequential(nn.Linear(d_model, dim_feedforward), nn.ReLU(inplace=True), nn.Dropout(dropout),
                                 nn.Linear(dim_feedforward, d_model))
        self.norm1, self.norm2 = nn.LayerNorm(d_model), nn.LayerNorm(d_model)
        self.drop1, self.drop2 = nn.Dropout(dropout), nn.Dropout(dropout)

    def forward(self, x, pos, memory=None, mem_pos=None):
        q = x + pos
        if memory is None:
            k, v = q, x
        else:
            k, v = memory + mem_pos, memory
        x = self.norm1(x + self.drop1(self.attn(q, k, v, need_weights=False)[0]))
        return self.norm2(x + self.drop2(self.ffn(x)))


class DecoderLayer(nn.Module):
    """DETR's decoder layer: query self-attention, cross-attention to the memory, FFN (post-norm)."""

    def __init__(self, d_model: int, nhead: int, dim_feedforward: int, dropout: float) -> None:
        super().__init__()
        self.self_attn = nn.MultiheadAttention(d_model, nhead, dropout=dropout, batch_first=True)
        self.norm = nn.LayerNorm(d_model)
        self.drop = nn.Dropout(dropout)
        self.cross = AttentionLayer(d_model, nhead, dim_feedforward, dropout)

    def forward(self, tgt, query_pos, memory, mem_pos):
        q = tgt + query_pos
        tgt = self.norm(tgt + self.drop(self.self_attn(q, q, tgt, need_weights=False)[0]))
        return self.cross(tgt, query_pos, memory, mem_pos)


def sine_encoding_2d(hf: int, wf: int, dim: int) -> torch.Tensor:
    """(hf * wf, dim) DETR's 2-D sine encodings of a map's positions, row-major: half the channels encode the row
    index, half the column index."""
    half = dim // 2
    return torch.cat([sine_encoding(hf, half)[:, None, :].expand(hf, wf, half),
                      sine_encoding(wf, half)[None, :, :].expand(hf, wf, half)], dim=-1).reshape(hf * wf, dim)


class RowColumnEncoder(nn.Module):
    """The encoder's branches over a (B, d, Hf, Wf) map -> memory (B, Hf * Wf, d), their outputs added.

    Row and column branches: ``mode="lines"`` (the paper): one token per row (its Wf x d values through an fc
    layer) and per column; the tokens of a branch attend to each other. ``mode="axial"``: every position is a
    token attending within its row (row branch) or its column (column branch). The pixel branch (``pixel``):
    every position a token attending to every position. ``branches(x)`` gives the outputs before they are
    added, each (B, Hf, Wf, d), the pixel one last when present."""

    def __init__(self, d_model: int, nhead: int, num_layers: int, dim_feedforward: int, dropout: float,
                 fmap_size: tuple[int, int], mode: str, pixel: bool = True) -> None:
        super().__init__()
        hf, wf = fmap_size
        self.mode, self.fmap_size = mode, (hf, wf)
        if mode == "lines":
            self.row_proj = nn.Linear(wf * d_model, d_model)
            self.col_proj = nn.Linear(hf * d_model, d_model)
            row_pos, col_pos = sine_encoding(hf, d_model), sine_encoding(wf, d_model)  # a row's / column's index
        else:
            row_pos, col_pos = sine_encoding(wf, d_model), sine_encoding(hf, d_model)  # the position inside it
        self.register_buffer("row_pos", row_pos[None], persistent=False)
        self.register_buffer("col_pos", col_pos[None], persistent=False)

        def layers():
            return nn.ModuleList(AttentionLayer(d_model, nhead, dim_feedforward, dropout) for _ in range(num_layers))

        self.row_layers, self.col_layers = layers(), layers()
        self.pixel_layers = layers() if pixel else None
        self.register_buffer("pixel_pos", sine_encoding_2d(hf, wf, d_model)[None], persistent=False)

    def branches(self, x: torch.Tensor) -> tuple[torch.Tensor, ...]:
        b, d, hf, wf = x.shape
        grid = x.permute(0, 2, 3, 1)  # (B, Hf, Wf, d)
        if self.mode == "lines":
            rows = self.row_proj(grid.reshape(b, hf, wf * d))  # (B, Hf, d)
            cols = self.col_proj(grid.transpose(1, 2).reshape(b, wf, hf * d))  # (B, Wf, d)
        else:
            rows = grid.reshape(b * hf, wf, d)  # each row a sequence of its Wf positions
            cols = grid.transpose(1, 2).reshape(b * wf, hf, d)  # each column one of its Hf positions
        for layer in self.row_layers:
            rows = layer(rows, self.row_pos)
        for layer in self.col_layers:
            cols = layer(cols, self.col_pos)
        if self.mode == "lines":
            out = [rows[:, :, None, :].expand(b, hf, wf, d), cols[:, None, :, :].expand(b, hf, wf, d)]
        else:
            out = [rows.reshape(b, hf, wf, d), cols.reshape(b, wf, hf, d).transpose(1, 2)]
        if self.pixel_layers is not None:
            pixels = grid.reshape(b, hf * wf, d)
            for layer in self.pixel_layers:
                pixels = layer(pixels, self.pixel_pos)
            out.append(pixels.reshape(b, hf, wf, d))
        return tuple(out)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return sum(self.branches(x)).reshape(x.shape[0], -1, x.shape[1])


class LaneFormerHead(LaneHead):
    """LaneFormer: row-column attention encoder, lane-query decoder, set prediction (see the module docstring).

    It reads the last of the feature maps it is given (the backbone's stride-32 stage in the paper)."""

    # The constructor's parameters with a range, and what a good value of each is: checked by the constructor,
    # and by the config check under model.head.* before any work (one place to say it).
    SETTINGS = {
        "d_model": integer(4),
        "nhead": integer(1),
        "num_encoder_layers": integer(0),
        "num_decoder_layers": integer(1),
        "dim_feedforward": integer(1),
        "dropout": number(0, 1, high_open=True),
        "num_queries": integer(1),
        "num_points": integer(2),
        "max_lanes": integer(1),
        "row_column": one_of(*ROW_COLUMN_MODES),
        "cls_weight": number(0),
        "x_weight": number(0),
        "y_weight": number(0),
        "eos_coef": number(0),
        "aux_loss": boolean(),
        "pixel_attention": boolean(),
    }

    def __init__(
        self,
        in_channels: list[int],
        in_strides: list[int],
        image_size: tuple[int, int],
        d_model: int = 256,
        nhead: int = 8,
        num_encoder_layers: int = 1,
        num_decoder_layers: int = 2,
        dim_feedforward: int = 1024,
        dropout: float = 0.1,
        num_queries: int = 12,
        num_points: int = 72,
        max_lanes: int = 6,
        row_column: str = "lines",
        pixel_attention: bool = True,
        cls_weight: float = 1.0,
        x_weight: float = 5.0,
        y_weight: float = 5.0,
        eos_coef: float = 0.1,
        aux_loss: bool = True,
    ) -> None:
        check_settings(self.SETTINGS, locals(), "model.head")
        super().__init__(in_channels, in_strides, image_size)
        name = type(self).__name__
        if d_model % 4 or d_model % nhead:
            raise ValueError(f"{name}: d_model={d_model} must be a multiple of 4 (2-D sine encodings) and of "
                             f"nhead={nhead}")
        if num_queries < max_lanes:
            raise ValueError(f"{name}: num_queries={num_queries} must be >= max_lanes={max_lanes} (every lane is "
                             f"matched to its own query)")
        h, w = self.image_size
        stride = self.in_strides[-1]
        self.fmap_size = (math.ceil(h / stride), math.ceil(w / stride))
        self.num_queries, self.num_points, self.max_lanes = num_queries, num_points, max_lanes
        self.weights = {"cls_weight": cls_weight, "x_weight": x_weight, "y_weight": y_weight}
        self.eos_coef, self.aux_loss = eos_coef, bool(aux_loss)
        self.row_ys = row_ys(h, num_points)

        self.input_proj = nn.Conv2d(self.in_channels[-1], d_model, kernel_size=1)
        self.encoder = RowColumnEncoder(d_model, nhead, num_encoder_layers, dim_feedforward, dropout,
                                        self.fmap_size, row_column, pixel=pixel_attention)
        hf, wf = self.fmap_size
        self.register_buffer("mem_pos", sine_encoding_2d(hf, wf, d_model)[None], persistent=False)
        self.query_embed = nn.Embedding(num_queries, d_model)
        self.decoder = nn.ModuleList(DecoderLayer(d_model, nhead, dim_feedforward, dropout)
                                     for _ in range(num_decoder_layers))
        # DETR's transformer init: every matrix of the encoder and decoder Xavier-uniform (models/transformer.py,
        # Transformer._reset_parameters); the fc layers making row / column tokens are part of the encoder
        for module in (self.encoder, self.decoder):
            for weight in module.parameters():
                if weight.dim() > 1:
                    nn.init.xavier_uniform_(weight)
        self.decoder_norm = nn.LayerNorm(d_model)
        self.cls_layer = nn.Linear(d_model, 2)
        self.reg_layer = nn.Sequential(nn.Linear(d_model, d_model), nn.ReLU(inplace=True),
                                       nn.Linear(d_model, d_model), nn.ReLU(inplace=True),
                                       nn.Linear(d_model, 2 + num_points))
        # start: lanes begin near the bottom, end: above the middle, x: the centre (a neutral first guess)
        last = self.reg_layer[-1]
        nn.init.normal_(last.weight, 0.0, 0.01)
        with torch.no_grad():
            last.bias.zero_()
            last.bias[0], last.bias[1] = y_to_logit(0.9), y_to_logit(0.4)
            last.bias[2:] = 0.5

    # ------------------------------------------------------------------ forward
    def memory(self, features: list[torch.Tensor]) -> torch.Tensor:
        """The encoder's output (B, Hf * Wf, d) on the last feature map."""
        x = self.input_proj(features[-1])
        hf, wf = self.fmap_size
        # zero-pad then crop to the expected map size (no shape-dependent branch; as LaneATTHead)
        x = F.pad(x, (0, wf, 0, hf))[:, :, :hf, :wf]
        return self.encoder(x)

    def _predict(self, hidden: torch.Tensor) -> dict[str, torch.Tensor]:
        reg = self.reg_layer(hidden)
        return {"cls_logits": self.cls_layer(hidden), "start_y": y_from_logit(reg[..., 0]),
                "end_y": y_from_logit(reg[..., 1]), "xs": reg[..., 2:]}

    def forward(self, features: list[torch.Tensor]) -> dict[str, torch.Tensor]:
        """Raw outputs: cls_logits (B, Q, 2), start_y and end_y (B, Q) as fractions of the height (in
        [-Y_MARGIN, 1 + Y_MARGIN]; decoding clips them to the image), xs (B, Q, N)
        as fractions of the width at the rows ``self.row_ys``; in training mode (with aux_loss and more than
        one decoder layer) also aux_<key> (B, L-1, ...) of the earlier decoder layers."""
        memory = self.memory(features)
        b = memory.shape[0]
        query_pos = self.query_embed.weight[None].expand(b, -1, -1)
        tgt = torch.zeros_like(query_pos)
        hidden = []
        for layer in self.decoder:
            tgt = layer(tgt, query_pos, memory, self.mem_pos)
            hidden.append(tgt)
        out = self._predict(self.decoder_norm(hidden[-1]))
        if self.training and self.aux_loss and len(hidden) > 1:
            aux = self._predict(self.decoder_norm(torch.stack(hidden[:-1], dim=1)))  # (B, L-1, Q, ...)
            out.update({f"aux_{k}": v for k, v in aux.items()})
        return out

    # ------------------------------------------------------------------ targets and loss
    def encode(self, lanes: list[np.ndarray], meta: dict | None = None) -> dict[str, np.ndarray]:
        """GT lanes (input pixels) -> {"lanes": (max_lanes, 3 + N) [valid, start_y, end_y, xs], "x_mask":
        (max_lanes, N)}, float32, in fractions of the image (loss.encode_lanes)."""
        return encode_lanes(lanes, self.image_size, self.num_points, self.max_lanes)

    def loss(self, raw: dict, targets: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """Hungarian-matched set loss of the last decoder layer (cls_loss, x_loss, y_loss: unweighted parts) plus
        the same loss of every earlier layer (aux_loss, weighted) when their outputs are present."""
        device = raw["xs"].device
        lanes = targets["lanes"].to(device).float()
        x_mask = targets["x_mask"].to(device).float()
        if lanes.ndim != 3 or lanes.shape[-1] != 3 + self.num_points or x_mask.shape != lanes[..., 3:].shape:
            raise ValueError(f"{type(self).__name__}.loss: targets lanes must be (B, max_lanes, "
                             f"{3 + self.num_points}) and x_mask (B, max_lanes, {self.num_points}), got "
                             f"{tuple(lanes.shape)} and {tuple(x_mask.shape)}")
        kw = {**self.weights, "eos_coef": self.eos_coef}
        main = set_loss(raw["cls_logits"], raw["start_y"], raw["end_y"], raw["xs"], lanes, x_mask, **kw)
        aux_b = torch.zeros_like(main["total"])
        if "aux_cls_logits" in raw:
            for i in range(raw["aux_cls_logits"].shape[1]):
                layer = set_loss(raw["aux_cls_logits"][:, i], *(raw[f"aux_{k}"][:, i] for k in _PARTS), lanes,
                                 x_mask, **kw)
                aux_b = aux_b + layer["total"]
        per_sample = main["total"] + aux_b
        return {"loss": per_sample.mean(), "cls_loss": main["cls"].mean(), "x_loss": main["x"].mean(),
                "y_loss": main["y"].mean(), "aux_loss": aux_b.mean(), "per_sample": per_sample}

    # ------------------------------------------------------------------ decode
    def decode(self, raw: dict, conf_threshold: float = 0.5, *,
               with_scores: bool = False) -> list[list[np.ndarray]] | list[list[tuple[np.ndarray, float]]]:
        """Per image: the lanes of the queries whose lane probability exceeds conf_threshold (no NMS: the set
        loss makes the queries one per lane), each the rows between its end y and start y, in input pixels,
        y descending, only points inside the image; sorted left to right by their bottom x. `with_scores`:
        (lane, score) pairs, the score the query's lane probability (the softmax of its class logits, last layer)."""
        h, w = self.image_size
        scores = torch.softmax(raw["cls_logits"].detach().float(), dim=-1)[..., 1].cpu().numpy()
        start = raw["start_y"].detach().float().cpu().numpy() * (h - 1)
        end = raw["end_y"].detach().float().cpu().numpy() * (h - 1)
        xs = raw["xs"].detach().float().cpu().numpy().astype(np.float64) * (w - 1)
        out: list[list[np.ndarray]] = []
        for b in range(scores.shape[0]):
            lanes, lane_scores = [], []
            for q in np.nonzero(scores[b] > conf_threshold)[0]:
                lane = assemble_lane(xs[b, q], start[b, q], end[b, q], self.row_ys, self.image_size)
                if lane is not None:
                    lanes.append(lane)
                    lane_scores.append(scores[b, q])
            out.append(lanes_with_scores(lanes, lane_scores, with_scores))
        return out
