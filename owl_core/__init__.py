"""owl_core: the OWL engine (looming, perceived rotation, RoT, heading) over numpy and OpenCV.

Imports numpy, cv2, scipy and the standard library only; no ROS, no bag formats.
"""
