"""What both sites agree on: object models, the scene layout, the robot and the camera."""

from models.errors import ModelError
from models.geometry import ConvexPart
from models.robot import HOME_Q, PUMA_URDF, RobotModel, load_robot
from models.scene import (
    DEFAULT_SCENE,
    CameraModel,
    ObjectModel,
    RobotPlacement,
    Scene,
    SceneObject,
    load_camera,
    load_object,
    load_scene,
)

__all__ = [
    "DEFAULT_SCENE",
    "HOME_Q",
    "PUMA_URDF",
    "CameraModel",
    "ConvexPart",
    "ModelError",
    "ObjectModel",
    "RobotModel",
    "RobotPlacement",
    "Scene",
    "SceneObject",
    "load_camera",
    "load_object",
    "load_robot",
    "load_scene",
]
