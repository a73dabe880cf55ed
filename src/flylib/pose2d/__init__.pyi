"""flylib.pose2d's names and the modules they come from.

``flylib/pose2d/__init__.py`` reads this file (``lazy_loader.attach_stub``) and loads each
module on first use of one of its names: torch comes with the model, not with the plan.
"""

from .inference import (
    LoadedModel as LoadedModel,
    load_models as load_models,
    select_device as select_device,
)
from .model import HourglassNet as HourglassNet
from .plan import (
    DetectionPlan as DetectionPlan,
    ModelSpec as ModelSpec,
    Pathway as Pathway,
    parse_op as parse_op,
)
from .stream import (
    detect_2d as detect_2d,
    detect_recording as detect_recording,
    run_detection as run_detection,
)
from .weights import (
    cache_dir as cache_dir,
    load_detector as load_detector,
    load_hourglass as load_hourglass,
    resolve_weights as resolve_weights,
    save_checkpoint as save_checkpoint,
)
