"""Run in the LeRobot environment: what LeRobot's own policies make of an exported dataset.

Usage: python policy_features.py DATASET_ROOT  (prints JSON)
(or ``report``, from ``lerobot_server.py``: one interpreter for a test module's loads)

Loads the dataset with ``lerobot``'s ``LeRobotDataset``, derives the policy
features with its ``dataset_to_policy_features`` and hands them to
``ACTConfig`` and ``DiffusionConfig`` as LeRobot's training script does
(every action feature an output, every other one an input). Each policy is
also asked with a camera's feature added (``observation.images.camera``,
3x480x640) when the dataset has none: whether the rest of the features are
all it still lacks.
"""

import json
import sys
import types

# torchvision's operator registrations need its CUDA build (see load_with_lerobot.py)
sys.modules["torchvision._meta_registrations"] = types.ModuleType("torchvision._meta_registrations")

from lerobot.configs.types import FeatureType, PolicyFeature  # noqa: E402
from lerobot.datasets.lerobot_dataset import LeRobotDataset  # noqa: E402
from lerobot.datasets.utils import dataset_to_policy_features  # noqa: E402
from lerobot.policies.act.configuration_act import ACTConfig  # noqa: E402
from lerobot.policies.diffusion.configuration_diffusion import DiffusionConfig  # noqa: E402


def report(root: str) -> dict:
    """What ACT and Diffusion make of the dataset at ``root`` (module docstring)."""
    ds = LeRobotDataset("deepxpalm/export", root=root)
    features = dataset_to_policy_features(ds.meta.features)
    outputs = {k: f for k, f in features.items() if f.type is FeatureType.ACTION}
    inputs = {k: f for k, f in features.items() if k not in outputs}
    item = ds[0]
    answer = {
        "features": {k: [f.type.name, list(f.shape)] for k, f in features.items()},
        "state_names": ds.meta.features["observation.state"]["names"],
        "action_names": ds.meta.features["action"]["names"],
        "first_state": item["observation.state"].tolist(),
        "first_action": item["action"].tolist(),
        "policies": {},
    }
    for name, cls in (("act", ACTConfig), ("diffusion", DiffusionConfig)):
        cfg = cls(input_features=inputs, output_features=outputs)
        entry = {
            "robot_state": None
            if cfg.robot_state_feature is None
            else list(cfg.robot_state_feature.shape),
            "action": None if cfg.action_feature is None else list(cfg.action_feature.shape),
            "images": sorted(cfg.image_features),
        }
        try:
            cfg.validate_features()
            entry["accepted"] = True
        except ValueError as e:
            entry["accepted"] = False
            entry["refusal"] = str(e)
        # a dataset without a camera gets one (Diffusion wants every image the same shape, so a
        # dataset with its own camera is asked as it is)
        camera = {"observation.images.camera": PolicyFeature(FeatureType.VISUAL, (3, 480, 640))}
        if cfg.image_features:
            camera = {}
        with_camera = cls(input_features={**inputs, **camera}, output_features=outputs)
        try:
            with_camera.validate_features()
            entry["accepted_with_a_camera"] = True
        except ValueError as e:
            entry["accepted_with_a_camera"] = str(e)
        answer["policies"][name] = entry
    return answer


if __name__ == "__main__":
    print(json.dumps(report(sys.argv[1])))
