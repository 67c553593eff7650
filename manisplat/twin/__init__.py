"""The twin a reconstruction leaves: load it from its folder and render any state.

    >>> from manisplat.twin import Twin
    >>> twin = Twin.load("demo_twin")                      # twin.json + twin.pt, no episode needed
    >>> view = twin.render(q, gripper, {"box": T_base_box})  # rgb uint8, depth m, labels
"""

from manisplat.twin.twin import Demonstration, Phase, Twin, TwinFormatError, TwinView

__all__ = ["Demonstration", "Phase", "Twin", "TwinFormatError", "TwinView"]
