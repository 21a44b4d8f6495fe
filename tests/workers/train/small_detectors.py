"""A small R-CNN configuration for tests: the plumbing under test, not learning."""

SMALL = {
    "input_size": 64,
    "fpn_channels": 32,
    "representation_size": 64,
    "rpn_proposals_train": 40,
    "rpn_proposals_test": 20,
    "roi_samples_per_image": 32,
    "edge_boxes": 30,
}
