"""Fast R-CNN (Girshick 2015): RoI heads on a backbone, fed external Edge Boxes proposals.

torchvision's pieces (GeneralizedRCNNTransform, MultiScaleRoIAlign, TwoMLPHead,
FastRCNNPredictor, RoIHeads) without the region proposal network: the proposals come from
``edge_boxes.py``, computed on each image as given (original pixels), cached by image
content, and rescaled into the network's input frame. In training, RoIHeads adds the
ground-truth boxes to the proposals (standard Fast R-CNN practice); inference never sees
ground truth.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import Tensor, nn

from workers.train.detectors.edge_boxes import ProposalCache, shared_cache
from workers.train.detectors.views import detect_at_views

if TYPE_CHECKING:
    from foldwise.config import DetectorConfig


def tensor_to_uint8(image: Tensor) -> np.ndarray:
    """A (3, H, W) float image in 0..1 back to (H, W, 3) uint8, exactly inverting x / 255."""
    return image.detach().mul(255).round_().clamp_(0, 255).to(torch.uint8).permute(1, 2, 0).cpu().numpy()


class FastRCNN(nn.Module):
    """Torchvision-style detector whose region proposals are precomputed Edge Boxes."""

    def __init__(
        self,
        backbone: nn.Module,
        transform: nn.Module,
        roi_heads: nn.Module,
        max_proposals: int,
        test_sizes: Sequence[int] = (),
        test_turns: Sequence[int] = (),
        view_vote: float | None = None,
    ) -> None:
        super().__init__()
        self.backbone = backbone
        self.transform = transform
        self.roi_heads = roi_heads
        self.max_proposals = max_proposals
        # Eval-mode detection at each of these input sizes and quarter turns, merged
        # (``detect_at_views``).
        self.test_sizes = tuple(test_sizes)
        self.test_turns = tuple(test_turns)
        self.view_vote = view_vote

    @property
    def proposal_cache(self) -> ProposalCache:
        return shared_cache(self.max_proposals)

    def proposals_for(self, image: Tensor) -> Tensor:
        """Edge Boxes of one (3, H, W) image, in its pixels (from the cache when seen before)."""
        boxes = self.proposal_cache.proposals(tensor_to_uint8(image))
        return torch.as_tensor(np.array(boxes), dtype=torch.float32, device=image.device)

    def forward(self, images: list[Tensor], targets: list[dict[str, Tensor]] | None = None):
        if not self.training and (self.test_sizes or self.test_turns):
            return detect_at_views(
                self, lambda views: self._forward(views, None), images, self.test_sizes, self.test_turns
            )
        return self._forward(images, targets)

    def _forward(self, images: list[Tensor], targets: list[dict[str, Tensor]] | None):
        if self.training and targets is None:
            raise ValueError("FastRCNN: targets are required in training mode")
        for image in images:
            if image.dim() != 3 or image.shape[0] != 3:
                raise ValueError(f"FastRCNN: expected (3, H, W) images, got shape {tuple(image.shape)}")
        original_sizes = [(int(image.shape[-2]), int(image.shape[-1])) for image in images]
        proposals = [self.proposals_for(image) for image in images]

        image_list, targets = self.transform(images, targets)
        for index, ((height, width), (new_height, new_width)) in enumerate(zip(original_sizes, image_list.image_sizes)):
            scale = proposals[index].new_tensor([new_width / width, new_height / height] * 2)
            proposals[index] = proposals[index] * scale

        features = self.backbone(image_list.tensors)
        if isinstance(features, Tensor):
            features = OrderedDict([("0", features)])
        detections, losses = self.roi_heads(features, proposals, image_list.image_sizes, targets)
        if self.training:
            return losses
        return self.transform.postprocess(detections, image_list.image_sizes, original_sizes)


def build_fast_rcnn(config: DetectorConfig, num_classes: int, load_pretrained: bool = True) -> FastRCNN:
    """A Fast R-CNN for ``num_classes`` object classes (+ background) on ``config.backbone``."""
    from torchvision.models.detection.faster_rcnn import FastRCNNConvFCHead, FastRCNNPredictor, TwoMLPHead
    from torchvision.models.detection.roi_heads import RoIHeads
    from torchvision.models.detection.transform import GeneralizedRCNNTransform

    from workers.train.detectors.backbones import build_backbone, feature_map_names, input_normalization
    from workers.train.detectors.roi_align import PyramidRoIAlign

    backbone = build_backbone(config, load_pretrained)
    # One bilinear sample per bin (torchvision: 2x2), and a backward pass that gathers rather than
    # scatters per channel (roi_align.py): RoIAlign's CPU backward dominated a step.
    roi_pool = PyramidRoIAlign(featmap_names=feature_map_names(backbone), output_size=7, sampling_ratio=1)
    if config.backbone == "resnet50_fpn_v2":
        box_head = FastRCNNConvFCHead(
            (backbone.out_channels, 7, 7), [256, 256, 256, 256], [config.representation_size], norm_layer=nn.BatchNorm2d
        )
    else:
        box_head = TwoMLPHead(backbone.out_channels * 7 * 7, config.representation_size)
    roi_heads = RoIHeads(
        roi_pool,
        box_head,
        FastRCNNPredictor(config.representation_size, num_classes + 1),
        fg_iou_thresh=0.5,
        bg_iou_thresh=0.5,
        batch_size_per_image=config.roi_samples_per_image,
        positive_fraction=0.25,
        bbox_reg_weights=None,
        score_thresh=config.box_score_threshold,
        nms_thresh=0.5,
        detections_per_img=config.detections_per_image,
    )
    image_mean, image_std = input_normalization(config)
    transform = GeneralizedRCNNTransform(
        min_size=config.input_size, max_size=config.input_size, image_mean=image_mean, image_std=image_std
    )
    return FastRCNN(
        backbone,
        transform,
        roi_heads,
        max_proposals=config.edge_boxes,
        test_sizes=config.test_sizes,
        test_turns=config.test_turns,
        view_vote=config.view_vote,
    )
