"""``eyeserver pose``: the eye pose of a measurement bundle, as JSON."""

from __future__ import annotations

import argparse
import json
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from eyeserver.commands import Subparsers
from eyeserver.commands import progress as _progress
from eyeserver.errors import EyeserverError

if TYPE_CHECKING:
    from eyeserver.eye import EyeModel

# The population model's values, for the help text only (the pipeline is not imported to
# build the parser); a test holds them equal to EyeModel.population().
POPULATION_CORNEA_RADIUS_MM = 7.8
POPULATION_LIMBUS_DIAMETER_MM = 11.7


@dataclass(frozen=True)
class Biometry:
    """One measure of the patient's eye the command takes: its flag, the
    :class:`~eyeserver.eye.fit.EyeModel` field it sets and the values accepted (mm)."""

    flag: str
    field: str
    least_mm: float
    most_mm: float

    @property
    def dest(self) -> str:
        """The attribute argparse stores the flag's value in."""
        return self.flag.removeprefix("--").replace("-", "_")

    def parse(self, text: str) -> float:
        """The value of ``text`` in mm; :class:`argparse.ArgumentTypeError` (argparse names the
        flag and exits with status 2) when it is not a number within the accepted range."""
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"not a length in mm: {text!r}") from None
        if not self.least_mm <= value <= self.most_mm:  # NaN fails too
            raise argparse.ArgumentTypeError(
                f"must be between {self.least_mm:g} and {self.most_mm:g} mm, not {text}")
        return value


# Wider than the healthy adult eye on purpose, meant to let a child's eye, high myopia,
# microcornea or keratoconus pass: what they catch is a wrong quantity or unit (a diameter for a
# radius, an axial length, cm for mm) or a typing slip.
GLOBE_RADIUS = Biometry("--globe-radius", "globe_radius_mm", 8.0, 16.0)
CORNEA_RADIUS = Biometry("--cornea-radius", "cornea_radius_mm", 5.0, 11.0)
LIMBUS_DIAMETER = Biometry("--limbus-diameter", "limbus_diameter_mm", 8.0, 15.0)
BIOMETRY = (GLOBE_RADIUS, CORNEA_RADIUS, LIMBUS_DIAMETER)
# The given radius's error (the API's globe_sd_mm): up to 2 mm, beyond which it is no MRI's.
GLOBE_SD = Biometry("--globe-radius-sd", "globe_sd_mm", 0.0, 2.0)
# The MRI's typical error, for the help text only; a test holds it equal to the fit's default.
MEASURED_GLOBE_SD_MM = 0.2


def add_parser(subparsers: Subparsers) -> None:
    """Register ``eyeserver pose --calibration CALDIR [biometry] BUNDLE``."""
    parser = subparsers.add_parser(
        "pose", help="the eye pose of a measurement bundle (JSON)",
        description="Reconstruct the measurement in BUNDLE with the calibration in CALDIR, fit "
        "the eye model with the limbus found in the fringe images, and print the pose as JSON: "
        "centre_mm (globe centre) and gaze (unit vector) in the WCS, with uncertainties, the "
        "surface-to-model distance and a confidence. The eye model is the patient's biometry "
        "where it is given (e.g. from the treatment plan's eye model) and the population "
        "model where it is not: globe radius fitted to the measured sclera, cornea radius "
        f"{POPULATION_CORNEA_RADIUS_MM:g} mm, limbus diameter "
        f"{POPULATION_LIMBUS_DIAMETER_MM:g} mm. The JSON's \"model\" records the values used "
        "and where each came from. Exit status 2 for biometry out of range or inconsistent, "
        "or when no eye is found.")
    parser.add_argument("--calibration", type=Path, required=True, metavar="CALDIR")
    biometry = parser.add_argument_group(
        "the patient's biometry", "All lengths in mm, each optional: a value not given is the "
        "population model's (the globe's radius fitted). Half the limbus diameter must be "
        "smaller than the cornea radius and the globe radius.")
    biometry.add_argument(
        GLOBE_RADIUS.flag, type=GLOBE_RADIUS.parse, metavar="MM",
        help="the globe's radius (a sphere), held by the fit: an error in it moves the "
        "globe centre along the gaze by a little more (0.3 mm too large moved a simulated "
        "12-mm eye's centre 0.4 mm deeper); accepted "
        f"{GLOBE_RADIUS.least_mm:g}–{GLOBE_RADIUS.most_mm:g} mm. Not given: fitted to the "
        "measured sclera (the output's globe_radius_mm)")
    biometry.add_argument(
        GLOBE_SD.flag, type=GLOBE_SD.parse, metavar="MM",
        help="the error (1 sd) of --globe-radius, e.g. from repeat MRI scans: the fit turns it "
        "into the uncertainty of the centre's depth (the output's shape_sd_mm); accepted "
        f"{GLOBE_SD.least_mm:g}–{GLOBE_SD.most_mm:g} mm, only with --globe-radius. Not given: "
        f"{MEASURED_GLOBE_SD_MM:g} mm (an MRI's typical error)")
    biometry.add_argument(
        CORNEA_RADIUS.flag, type=CORNEA_RADIUS.parse, metavar="MM",
        help="the anterior cornea's radius of curvature (keratometry); accepted "
        f"{CORNEA_RADIUS.least_mm:g}–{CORNEA_RADIUS.most_mm:g} mm. Not given: "
        f"{POPULATION_CORNEA_RADIUS_MM:g} mm (population)")
    biometry.add_argument(
        LIMBUS_DIAMETER.flag, type=LIMBUS_DIAMETER.parse, metavar="MM",
        help="the limbus's diameter (horizontal white-to-white, the visible iris across); "
        f"accepted {LIMBUS_DIAMETER.least_mm:g}–{LIMBUS_DIAMETER.most_mm:g} mm. Not given: "
        f"{POPULATION_LIMBUS_DIAMETER_MM:g} mm (population)")
    parser.add_argument("bundle", type=Path, metavar="BUNDLE")
    parser.set_defaults(handler=_pose)


def eye_model(args: argparse.Namespace) -> tuple[EyeModel, dict[str, Any]]:
    """The eye model of the parsed biometry flags, and its record for the JSON output.

    Raises
    ------
    EyeserverError
        Half the limbus diameter is not smaller than the cornea radius or the globe radius
        (the limbus is where the cornea meets the globe).
    """
    from eyeserver.eye import EyeModel

    given = {item.field: getattr(args, item.dest) for item in BIOMETRY
             if getattr(args, item.dest) is not None}
    globe_sd = getattr(args, GLOBE_SD.dest, None)
    if globe_sd is not None:
        if GLOBE_RADIUS.field not in given:
            raise EyeserverError(f"{GLOBE_SD.flag} {globe_sd:g} mm is the error of "
                                 f"{GLOBE_RADIUS.flag}, which is not given (the radius is "
                                 "fitted, its error the fit's)")
        given[GLOBE_SD.field] = globe_sd
    model = replace(EyeModel.population(), **given)
    _check_limbus_fits(model, given)
    record: dict[str, Any] = {item.field: getattr(model, item.field) for item in BIOMETRY}
    record["source"] = {item.field: "given" if item.field in given
                        else "fitted" if item.field == GLOBE_RADIUS.field
                        else "population default" for item in BIOMETRY}
    # A given radius carries its error into the pose; a fitted one carries the fit's.
    held = GLOBE_RADIUS.field in given
    record[GLOBE_SD.field] = model.globe_sd_mm if held else None
    record["source"][GLOBE_SD.field] = ("given" if GLOBE_SD.field in given
                                        else "an MRI's typical error" if held else "fitted")
    return model, record


def _check_limbus_fits(model: EyeModel, given: dict[str, float]) -> None:
    def described(item: Biometry) -> str:
        how = "given" if item.field in given else "population default"
        return f"{item.flag} {getattr(model, item.field):g} mm, {how}"

    half = model.limbus_diameter_mm / 2
    too_small = [f"the {name} radius ({described(item)})"
                 for name, item in (("cornea", CORNEA_RADIUS), ("globe", GLOBE_RADIUS))
                 if getattr(model, item.field) is not None
                 and half >= getattr(model, item.field)]
    if too_small:
        raise EyeserverError(
            f"half the limbus diameter, {half:g} mm ({described(LIMBUS_DIAMETER)}), must be "
            f"smaller than {' and than '.join(too_small)}: the limbus is where the cornea "
            "meets the globe")


def _pose(args: argparse.Namespace) -> int:
    from eyeserver.eye import fit_eye
    from eyeserver.reconstruction import limbus_views, reconstruct_bundle

    # Checked before the reconstruction's seconds are spent.
    model, model_record = eye_model(args)
    cloud, _ = reconstruct_bundle(args.calibration, args.bundle, progress=_progress)
    views = limbus_views(args.calibration, args.bundle)
    # PoseError → "eyeserver: error: …", exit 2
    pose = fit_eye(cloud, model, views)
    print(json.dumps({**pose.to_dict(), "model": model_record}, indent=1))
    return 0
