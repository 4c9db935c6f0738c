"""CLRerNet (Honda & Uchida, "CLRerNet: Improving Confidence of Lane Detection with LaneIoU", WACV 2024): CLRNet's
head (models/clrnet) trained with LaneIoU as the assignment cost and the IoU loss (laneiou.py, head.py); its
published files (official.py).

Facts of the official code (hirotomusiker/CLRerNet, main at 21761ed, Apache-2.0; file:line at that commit unless
named; the published weights are release v0.1.0, 0b28a23, whose head, anchors, attention, FPN and DLA have the same
names and shapes):

- LaneIoU (libs/models/losses/iou_loss.py:56-106, LaneIoULoss; libs/core/bbox/match_costs/match_cost.py:132-254,
  LaneIoUCost): x are fractions of the width (the loss: pred x (W-1) / W and target / W, clrernet_head.py:336-338;
  the assigner: both / (W-1), dynamic_topk_assigner.py:205-206). Per row i the virtual half width is
  ``lane_width x sqrt(dx^2 + dy^2) / dy`` with dx = (x[i+1] - x[i-1]) x img_w and dy = img_h / n_strips x 2
  (iou_loss.py:81-96; rows 0 and S-1 take their neighbour's, l. 88-90, 94-96); img_h = 320, img_w = 1640 are the
  classes' defaults (iou_loss.py:58, match_cost.py:134-141), which no CULane config overrides: the angle is measured
  in the 1640 x 320 crop of the original image below the cut, not in the 800 x 320 input (the CurveLanes draft
  branch passes the evaluation's shape instead, ``eval_shape`` = (crop_h / ori_h x 224, 224), feature/curvelanes
  33add07 libs/datasets/curvelanes_dataset.py:51-54). The prediction's widths are computed from a detached copy
  (l. 83); a target's |dx| > max_dx = 1e4 (an undefined row next to a defined one) counts as 0 (l. 66, 92).
  Overlap = min(p + wp, t + wt) - max(p - wp, t - wt) (negative when apart), union = max(..) - min(..)
  (match_cost.py:97-108); IoU = sum of overlaps / (sum of unions + 1e-9) (iou_loss.py:44).
  - rows counted: in the loss and the dynamic k, the target's rows with x in [0, 1) (iou_loss.py:37-43,
    match_cost.py:213-233); in the cost (``use_pred_start_end``), the rows where both lie in [0, 1) and the row index
    is in [int(start x n_strips), int(end x n_strips)), start = clamp(1 - y0, 0, 1), end = clamp(start + length, 0, 1)
    (dynamic_topk_assigner.py:162-167, match_cost.py:181-200); a row where only the prediction (or only the target)
    counts adds 2 x its half width to the union (match_cost.py:202-210).
- The assignment (DynamicTopkAssigner, cost_combination 1; dynamic_topk_assigner.py:53-84, 145-180, 182-223): cost =
  focal cost (FocalCost: sigmoid of the positive logit, alpha 0.25, gamma 2, match_cost.py:7-34) - reg_weight x
  (1 - (1 - IoU_cost) / max(1 - IoU_cost) + 0.01), reg_weight 3.0 (l. 37, 174, 179), IoU_cost the LaneIoU at half
  width 30/800 with the prediction's rows; k per lane = max(min_topk, int(sum of the max_topk = 4 largest LaneIoUs at
  7.5/800 over the target's rows, negatives as 0)) (l. 64-67; base_clrernet.py:52-71); each lane takes its k
  lowest-cost priors (l. 69-73); a prior taken twice keeps its lowest-cost lane, the whole row cleared (l. 76-80,
  fixed at 72c6c8c; before it only column 0 was cleared).
- The loss (clrernet_head.py:253-357): per stage and image, KorniaFocalLoss (alpha 0.25, gamma 2, weight 2.0) summed
  over the priors / the image's lane count, smooth-L1 (weight 0.2) of (y0, x0, theta, length) in rows, pixels of
  W - 1, degrees and rows averaged over the matched priors, 1 - LaneIoU (half width 7.5/800, weight 4.0) averaged
  over them; all / (batch x stages) (l. 340-343; weights base_clrernet.py:35-48); the auxiliary segmentation
  (weight 1.0, 4 + 1 classes, background 0.4; CLRNetSegLoss, seg_loss.py:7-20: CLRNet's weighted mean).
  The length target is shortened by (prediction start - target start) counted from the TOP (y0 rows,
  l. 318-326 with lane_formatting.py:70-72), i.e. lengthened where CLRNet shortens it.
- Anchors (libs/core/anchor/anchor_generator.py): ``prior_embeddings`` nn.Embedding(192, 3) [y0, x0, theta], y0 the
  start's y from the top as a fraction of H (CLRNet's start_y is 1 - y0; init l. 31-62: side priors y0 = 1 -
  (i // 2) x 0.5 / 11, bottom priors y0 = 1); x at the rows prior_ys = linspace(1, 0, 72): (x0 (W-1) - (ys - y0)
  img_h / tan(theta pi + 1e-5)) / (W-1) (l. 81-92): CLRNet's lines with the rows spanning img_h.
- The head (libs/models/dense_heads/clrernet_head.py): buffers sample_x_indices = int(linspace(0, 1, 36) x 71),
  prior_feat_ys = flip(sample_x_indices / 71), prior_ys = linspace(1, 0, 72) (l. 66-82); ROI features pooled with x
  at sample_x_indices (bottom row first) and y = prior_feat_ys x 2 - 1 (l. 120-150, 192: the x flip CLRNet makes is
  commented out), so sample j reads the x of row index[j] at the height of row 71 - index[35 - j] (one row above
  where 71 j / 35 is not whole); stage refinement as CLRNet's (l. 191-249: y0, x0, theta += reg[:3]; length = reg[3];
  xs = anchor x + reg[4:]); reg_layers (76, 64), cls_layers (2, 64), {cls,reg}_modules 2 x (Linear, ReLU)
  (l. 84-98); the segmentation decoder only when its loss weight > 0 (l. 58, 101-109).
- ROIGather (libs/models/layers/attentions.py): convs / catconv ConvModules (9, 1) with BN (l. 46-69), fc + fc_norm
  (l. 71-72), its cross attention a child ``attention`` (AnchorVecFeatureMapAttention: f_key ConvModule 1x1 + BN,
  f_query grouped Conv1d + ReLU, f_value, W zero-initialised, key and value resized to (10, 25); l. 156-245): CLRNet's.
- Decoding (clrernet_head.py:401-527; configs/clrernet/base_clrernet.py:73-86): softmax score >= conf_threshold
  (0.41 for clrernet_culane_dla34.py:22, 0.43 for the EMA model, clrernet_culane_dla34_ema.py:22), NMS 50 px on
  x (W-1) with start 1 - y0 and length x n_strips (CLRNet's kernel, l. 436-454), top 4; start = round((1 - y0) x 71),
  length = round(length x 71), end = min(start + length - 1, 71) (l. 460, 491-497); extended down while inside
  [0, 1] (l. 498-500); then EVERY row from the start to the end (l. 501-504: no x >= 0 filter, unlike CLRNet); y =
  (prior_ys x (590 - 270) + 270) / 590 (l. 506-509); lanes of <= 1 point dropped; the ``Lane`` spline
  (libs/utils/lane_utils.py:5-30, CLRNet's). The CULane file (libs/datasets/metrics/culane_metric.py:81-106): the
  Lane at rows 0, 2, ..., 588 (y_step 2, l. 31, 89), 0 <= x < 1 kept, x 1640, "{:.5f} {:.5f}", bottom first,
  lanes of < 2 points left out.
- Data (configs/clrernet/culane/dataset_culane_clrernet.py): crop rows 270-590 of 1640 x 590 (l. 3), albumentations
  Resize to 800 x 320 (l. 4, 54-65: cv2.INTER_LINEAR, albumentations' default), BGR / 255 (base_clrernet.py:3-8:
  mean 0, std 255, bgr_to_rgb False); training: AdamW 6e-4, batch 24, 15 epochs (EMA: 50), cosine per iteration
  (clrernet_culane_dla34.py:24-55).

The code reuses CLRNet's head, ROIGather, priors, codec, NMS and decoding (models/clrnet) and its backbone and neck
renames; what differs is in head.py and laneiou.py.
"""

from lanevil_train.models.clrernet.head import CLRerNetHead

__all__ = ["CLRerNetHead"]
