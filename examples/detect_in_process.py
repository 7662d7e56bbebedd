"""Detection inside your own Python program: no Zenoh, no services (README, "Integrating").

    python examples/detect_in_process.py

``read_scan`` stands in for your LiDAR driver (here: the stand-in room of ``publish_scans.py``).
"""

from publish_scans import read_scan

from common.encoding import ScanStacker
from common.inference import OnnxDetector
from common.model_spec import default_model_path

detector = OnnxDetector(default_model_path())  # the shipped model, or $TRISCAN_MODEL
stacker = ScanStacker.for_model(detector)  # as the model reads scans: padding, invalid rule, raster yaw
for seq in range(30):  # 3 s of scans at 10 Hz
    angle_min, angle_increment, range_min, range_max, ranges = read_scan(seq / 10)
    tensor = stacker.push_scan(ranges, angle_min, angle_increment, range_min, range_max)
    if tensor is None:
        continue  # the first two scans only fill the stack
    detections, _ = detector.detect(tensor)  # boxes of the middle scan, in the laser frame
    found = [f"{d.class_name} {d.score:.2f} at ({d.x_m:+.2f}, {d.y_m:+.2f}) m" for d in detections]
    print(seq, ", ".join(found))
