"""The perceive job: one image pipeline over a log's images -> an MCAP of ImageMarker detections.

Every image (sensor_msgs/Image or CompressedImage) of the chosen topics goes through one pipeline
of :mod:`trundle.tools.jobs.image_pipelines`; its detections are written as
visualization_msgs/ImageMarker (stamped and framed like the image) with the image's log time. The
images and camera infos are copied into the output too (unless ``images=False``), so it opens on
its own, and so is ``/tf_static`` (the marker pipeline places the camera on the robot by it). A
corrupt message or image is counted and skipped, never fatal.
"""

from __future__ import annotations

import collections
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from trundle.logs import messages as m
from trundle.logs import ros2
from trundle.logs.errors import UserError
from trundle.logs.outputs import json_text, writing_file
from trundle.logs.paths import new_file
from trundle.logs.reader import LogReader, damage_dict
from trundle.logs.topics import TF_STATIC_TOPIC
from trundle.logs.writer import Logger
from trundle.perception.images import decode_image
from trundle.tools.jobs.image_pipelines import PIPELINES
from trundle.tools.jobs.progress import NoProgress, ProgressFactory

IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
CAMERA_INFO_TYPE = "sensor_msgs/msg/CameraInfo"
MAX_QUEUED = 500            # wait for the logger rather than let it drop messages


def camera_info_topic(image_topic: str) -> str:
    """``/ns/image_raw/compressed`` -> ``/ns/camera_info`` (the image_transport convention)."""
    namespace = image_topic.rsplit("/image", 1)[0] if "/image" in image_topic else image_topic.rsplit("/", 1)[0]
    return f"{namespace}/camera_info"


def _stats(values: list[int]) -> dict[str, float]:
    """Mean, min and max of the detections per frame (zeros without frames)."""
    if not values:
        return {"mean": 0.0, "min": 0, "max": 0}
    return {"mean": float(np.mean(values)), "min": int(min(values)), "max": int(max(values))}


def perceive_log(log: Path, output: Path, pipeline: str, options: Mapping[str, Any] | None = None,
                 topics: Sequence[str] | None = None, images: bool = True, camera_info: str | None = None,
                 provenance: Mapping[str, Any] | None = None,
                 progress: ProgressFactory = NoProgress) -> dict[str, Any]:
    """Run the ``pipeline`` (``color``, ``markers`` or ``features``) over the images of ``log``
    into the MCAP ``output``.

    ``options`` are the keyword arguments of the pipeline's class in
    :data:`trundle.tools.jobs.image_pipelines.PIPELINES`; ``topics`` the image topics (default:
    every Image and CompressedImage topic); ``images=False`` writes only the detections.
    ``camera_info`` is the CameraInfo topic of every image topic (default: each one's
    ``<camera namespace>/camera_info``); ``provenance`` (e.g. the command's arguments) is kept as
    JSON in the output's ``perceive`` metadata; ``progress`` shows the messages done. Returns the
    summary: what the log's damage skipped (``log_damage``, None when intact), frames, corrupt
    messages, detections per frame, the pipeline's totals and the messages written per topic.
    Outputs that overwrite the input are a UserError; on any failure (Ctrl-C included) nothing is
    left under ``output`` (:func:`trundle.logs.outputs.writing_file`).
    """
    if pipeline not in PIPELINES:
        raise UserError(f"unknown pipeline {pipeline!r} (choose from {', '.join(PIPELINES)})")
    if output.exists() and log.exists() and output.resolve() == log.resolve():
        raise UserError("the output must not be the input log")
    reader = LogReader(log)
    new_file(output, "output")
    info = reader.info()
    image_topics = sorted(t for t, i in info.topics.items() if i.ros_type in IMAGE_TYPES)
    topics = list(topics or image_topics)
    missing = [t for t in topics if t not in image_topics]
    if missing:
        raise UserError(f"not an image topic in {log.name}: {', '.join(missing)} "
                        f"(images: {', '.join(image_topics) or 'none'})")
    if not topics:
        raise UserError(f"no Image or CompressedImage topic in {log.name}")
    detector = PIPELINES[pipeline](**(options or {}))
    wanted = {camera_info_topic(t) for t in topics} | ({camera_info} if camera_info else set())
    info_topics = sorted(t for t in wanted if t in info.topics and info.topics[t].ros_type == CAMERA_INFO_TYPE)
    cameras: dict[str, m.CameraInfo] = {}
    frames, per_frame = 0, []
    corrupt: collections.Counter[str] = collections.Counter()
    bar = progress("perceive", sum(info.topics[t].count for t in topics))
    metadata = {"perceive": json_text(dict(provenance or {}))}
    with writing_file(output) as tmp, Logger(tmp, salvage=False, metadata=metadata) as logger:
        def write(topic: str, ros_type: str, data: bytes, log_time_ns: int) -> None:
            """Queue one encoded message, waiting while the logger is behind (so none is dropped)."""
            while logger.queue_length >= MAX_QUEUED and logger.error is None:
                time.sleep(0.001)
            logger.write_encoded(topic, ros_type, data, log_time_ns)

        static = [TF_STATIC_TOPIC] if TF_STATIC_TOPIC in info.topics else []
        for raw in reader.raw_messages(topics + info_topics + static):
            if images or raw.topic == TF_STATIC_TOPIC:
                write(raw.topic, raw.ros_type, raw.data, raw.log_time_ns)
            try:
                msg = ros2.decode(raw.ros_type, raw.data)
                if isinstance(msg, m.TFMessage):
                    detector.static_transforms(msg)
                    continue
                if isinstance(msg, m.CameraInfo):
                    cameras[raw.topic] = msg
                    continue
                if not isinstance(msg, (m.CompressedImage, m.Image)):
                    raise TypeError(f"{type(msg).__name__} is not an image")
                image = decode_image(msg)
            except Exception as error:  # a corrupt message or image is counted and skipped, never fatal
                corrupt[f"{raw.topic}: {type(error).__name__}: {error}"[:160]] += 1
                continue
            camera = cameras.get(camera_info or camera_info_topic(raw.topic))
            count, detections = detector.process(raw.topic, msg, image, camera)
            for topic, detection in detections:
                write(topic, *ros2.encode(detection), raw.log_time_ns)
            per_frame.append(count)
            frames += 1
            bar.update(frames + sum(corrupt.values()), f"{frames} frames")
        bar.close()
    return {"log": str(log), "log_damage": damage_dict(reader.last_damage), "output": str(output),
            "pipeline": pipeline, "image_topics": topics,
            "frames": frames, "corrupt_messages": sum(corrupt.values()), "corrupt_reasons": dict(corrupt),
            "detections_per_frame": _stats(per_frame), **detector.summary(),
            "written": {t: s.written for t, s in sorted(logger.stats.items())},
            "dropped": sum(s.dropped for s in logger.stats.values())}
