"""Strategy ``fused``: odometry, INS and the rail constraint in one least-squares smoothing.

Unknowns: the 6-DoF pose ``T_world_base`` of every frame (a small rotation vector, applied
on the left, and a position correction around an initial guess) and the INS-to-lidar
misalignment ``M = make_T(Exp(b), l)`` (boresight ``b`` 3, lever arm ``l`` 3 in the base
frame) with the INS latency ``L`` (1). With the nominal assumption the INS reports
``T_nom(t + L) = T_world_base(t) @ M`` (see :mod:`worker.synth.ins_sim` and
:class:`geometry.poses.InsToLidar`).

Residuals, each divided by its standard deviation:

- KISS-ICP relative motions between consecutive frames (translation in the earlier
  frame, rotation); the along-track component is down-weighted where the ICP problem is
  degenerate (per frame, and for the whole run when odometry is flagged), and frames
  whose ICP step disagrees with the INS speed are down-weighted;
- INS positions and attitude through the misalignment (the latency rotates the INS
  attitude sample by its angular rate: the heading lag in curves), weak, after removing
  detected GNSS jump steps; a Huber loss takes what remains of jumps and drift;
- the rail constraint when an ego centreline is known: the base origin on the centreline
  (lateral, and height along the canted rail-plane normal, sigma 5 cm: the fitted
  centreline's errors run along the track and many frames share them),
  the orientation near the centreline frame (heading from the tangent, pitch from the
  slope, roll from the cant); linearised at the current positions and re-linearised once;
- ground pairs (:mod:`~worker.preparation.localization.ground_pairs`): the height, roll and
  pitch of frame k + lag in frame k (lags 1 and 10) from the ground both frames see. KISS-ICP
  runs without the ground and drifts in pitch; the ground fixes exactly those three;
- the INS velocity: each step's displacement along the track (the INS's forward axis) and
  sideways (its world displacement on the solution's lateral axis);
- odometry pairs: frame k + lag's position in frame k (lags 10 and 30), along the track from
  KISS-ICP and across it from the fine scan-to-scan registration where that is sharper
  (:mod:`~worker.preparation.localization.scan_pairs`);
- a smoothness prior on the positions and rotations (second differences, per base axis), and
  priors on the misalignment (zero lever arm, boresight and latency).

Solved by Gauss-Newton with Huber weights (iteratively reweighted) on the sparse normal
equations, the Jacobian by grouped finite differences (a few dozen residual evaluations);
``scipy.optimize.least_squares`` with ``jac_sparsity`` converged too slowly with its
inexact (lsmr) trust-region steps.

Observability: the lever arm along the track and the latency (times the speed) move the
poses along the track exactly like the INS's own along-track error, which nothing here
observes: the poses follow the INS along the track, the along-track lever arm stays at its
zero prior, and the latency is estimated from the attitude lag only
(in curves). Without rails the misalignment is kept at the nominal assumption; at a
standstill only what the rails fix against the INS attitude is estimated. Those cases are
said in the health warnings / extras.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.linalg import LinAlgError, cho_factor, cho_solve, lapack
from scipy.ndimage import median_filter
from scipy.sparse import coo_matrix, csc_matrix, csr_matrix, diags, identity
from scipy.sparse.linalg import spsolve
from scipy.spatial.transform import Rotation

from geometry.pose_uncertainty import PoseInformation
from geometry.poses import InsToLidar, PoseTrack
from worker.preparation.localization.accelerometer import accel_block
from worker.preparation.localization.base import Health, LocalizationInput, LocalizationResult
from worker.preparation.localization.body_sway import oscillator_prior
from worker.preparation.localization.common import (
    InsFrames,
    ins_at_frames,
    make_result,
    poses_from,
    remove_jumps,
)
from worker.preparation.localization.ground_pairs import LAGS as GROUND_LAGS
from worker.preparation.localization.ground_pairs import ground_pairs
from worker.preparation.localization.gyro import GAP_SIGMA_FACTOR, gyro_steps
from worker.preparation.localization.hat import hat_variances, relative_difference
from worker.preparation.localization.heading_hat import MIN_PAIRS as HEADING_MIN_PAIRS
from worker.preparation.localization.heading_hat import HeadingErrors, heading_errors
from worker.preparation.localization.ins_wander import ins_wander, robust_rms
from worker.preparation.localization.lidar_yaw import (
    lidar_pitch_offset,
    lidar_yaw_offset,
    tilt_lidar_poses,
    turn_lidar_poses,
)
from worker.preparation.localization.odometry import (
    degenerate_frames,
    is_degenerate,
    odometry_deltas,
    odometry_run,
    odometry_track,
)
from worker.preparation.localization.rails import RailsStrategy, orientation_noise, rail_frames
from worker.preparation.localization.scan_errors import with_scan_errors
from worker.preparation.localization.scan_pairs import (
    closure_factor,
    register_pairs,
    register_to_map,
)
from worker.preparation.localization.step_noise import step_noise, white_noise

F64 = NDArray[np.float64]
log = logging.getLogger(__name__)

DEG = np.pi / 180.0


#: Metres of track the frames must cover for the rails' heading term to be loosened to
#: ``Sigmas.rail_heading_moving`` (their lateral positions then hold the heading). 5 m:
#: any moving train; at 20 m a 20-frame station sequence (11 m) kept the 0.05 deg floor
#: and its relative yaw followed the fitted curve's bends.
RAIL_HEADING_BASELINE_M = 5.0
#: Length of track (m) over which a fitted centreline's orientation errors are taken as one
#: (the fit's knots are 2 m apart and its smoothing spans several: NOISE_STEP_M x 2).
RAIL_CORRELATION_M = 8.0


@dataclass(frozen=True)
class Sigmas:
    """Standard deviations of the residual blocks (m, rad, s)."""

    odo_t: float = 0.006
    odo_r: float = 0.01 * DEG
    odo_t_degenerate: float = 2.0
    #: INS positions drift by centimetres to decimetres over seconds (GNSS multipath, the
    #: filter's own random walk): weighted as 0.1 m so that the odometry carries the
    #: frame-to-frame motion (at 5 cm the fused along-track step noise was 10 mm against
    #: KISS-ICP's 6; at 0.2 m a 3 m GNSS jump leaked into the poses).
    ins_p: float = 0.1
    ins_r: float = 0.03 * DEG
    #: The INS velocity as a step measurement (:func:`_velocity_steps`), its sigma bounds
    #: (m/s).
    use_ins_velocity: bool = True
    ins_v_bounds: tuple[float, float] = (0.005, 0.05)
    #: Scale the INS attitude sigma by sqrt(records within one knot spacing).
    ins_r_share: bool = True
    #: The base origin on the fitted centreline (m). Loose: the centreline is fitted from a
    #: cloud registered with the odometry's poses, its errors run along the track over
    #: metres, and tens of frames share them; at 1.5 / 1 cm they pinned the poses to those
    #: errors (C2 RPE 3.4 px on the bench against 2.9 with the odometry alone).
    rail_lat: float = 0.05
    rail_vert: float = 0.05
    #: Floor of the rail orientation sigmas (roll, pitch, heading). The sigmas used are the
    #: larger of this and the centreline's own measured orientation noise
    #: (:func:`~worker.preparation.localization.rails.orientation_noise`): a fitted
    #: centreline's tangent and slope are noisy over a few metres (0.2-0.4 deg on the
    #: synthetic fire_site, from cm noise on knots 2 m apart), and then the rails fix the
    #: orientation on average (through the positions on the centreline) while the odometry
    #: and INS attitude carry its changes. With the floor alone (0.05 deg) the fused jitter
    #: on rgb_highres_center was 1.5 px.
    #: Roll's floor is larger: the cant comes from two rail-head heights 1.435 m apart, and
    #: 1 cm of height error there is 0.4 deg (on the synthetic scenes the fitted cant
    #: wandered by 0.28 deg; with the 0.05 deg floor the fused roll followed it once the INS
    #: attitude's slow part was freed, and the C2 RPE rose by 0.4-0.9 px).
    rail_r: tuple[float, float, float] = (0.4 * DEG, 0.05 * DEG, 0.05 * DEG)
    #: The heading sigma once the frames cover RAIL_HEADING_BASELINE_M of track: the rails'
    #: lateral positions hold the heading over that baseline, and a fitted centreline's
    #: tangent errors are correlated along the track, more than its measured (white) noise
    #: says. Measured (C2 RPE over sub-cell placements of the ridge grid): station 1.5-3.7 px
    #: with the 0.05 deg floor, 1.4 px with this; a standing train keeps the floor (the
    #: track is its only heading).
    rail_heading_moving: float = 5.0 * DEG
    #: Second differences of the positions, along the middle frame's base (x along the
    #: track, y lateral, z up), m.
    acc: tuple[float, float, float] = (0.02, 0.02, 0.02)
    #: Second differences of the frame-to-frame rotation, about the base's (roll, pitch,
    #: heading) axes.
    rot_acc: tuple[float, float, float] = (0.02 * DEG, 0.02 * DEG, 0.02 * DEG)
    #: Third differences of the positions in the base frame (m), lateral and vertical: a
    #: train's jerk is limited (about 1 m/s^3 -> 1 mm over 0.1 s steps) and its body's sway
    #: on the suspension (a few mm at 1-2 Hz) stays within a few millimetres; constant
    #: curvature or acceleration costs nothing (unlike a tight second-difference prior,
    #: which fights the centripetal term of a tight curve). Along the track the INS speed
    #: carries the steps: a stiff along-track term (5 mm) left the absolute along-track
    #: position so weakly held that the dense and sparse solvers differed by 2e-6 m. None:
    #: no jerk prior.
    jerk: tuple[float, float, float] | None = (1.0, 0.003, 0.003)
    lever: float = 1.0
    boresight: float = 2.0 * DEG
    latency: float = 0.05
    huber: float = 3.0
    #: The INS's slow errors (its filter wandering by decimetres and tenths of a degree
    #: over seconds, as the real OSDaR23 INS does): an attitude bias (world rotation
    #: vector) and a position bias (world, m), linear between knots ``bias_knot_s`` apart,
    #: with a weak prior on their size and one on their change between knots. The change's
    #: sigma is the INS's wander against the odometry over one knot spacing, measured per
    #: sequence (:mod:`~worker.preparation.localization.ins_wander`), within the floor and
    #: cap below; the defaults when it cannot be measured. A good INS thus keeps carrying
    #: the slow attitude, a wandering one only the frame-to-frame motion. With a fixed
    #: sigma the wandering INS attitude (sigma 0.03 deg, the tightest absolute rotation
    #: term) dragged the poses with it (23 px on C2), or the rails' noisier orientation
    #: replaced a good INS's (2.4 -> 3.0 px).
    bias_knot_s: float = 1.0
    #: Ground pairs (:mod:`~worker.preparation.localization.ground_pairs`): frame offsets,
    #: and the sigmas of a pair's (height m, roll rad, pitch rad) as ``a + b * lag``, from
    #: their measured errors on the synthetic scenes (pitch 0.001 deg over 1 frame, 0.004
    #: over 10; height 1.3 and 4 mm; roll 0.006 and 0.011 deg).
    ground_lags: tuple[int, ...] = GROUND_LAGS
    ground_sigma_a: tuple[float, float, float] = (0.0015, 0.005 * DEG, 0.001 * DEG)
    ground_sigma_b: tuple[float, float, float] = (0.0003, 0.0006 * DEG, 0.0003 * DEG)
    #: Odometry pairs (:func:`_odometry_pairs`): KISS-ICP's relative pose of frames k and
    #: k + lag for these lags, with sigmas ``a + b * lag`` (m) of frame j's position in
    #: frame k along the track and laterally. Scan-to-map odometry does not drift like a
    #: chain of independent steps: its error is mostly a per-frame registration error of
    #: millimetres plus a slow drift, so its relative pose over 10 or 30 frames is far
    #: better than the lag-1 steps' random walk says (fire_site, 60 frames: 13 mm over 30
    #: frames where 30 independent 6 mm steps would be 33 mm). Its height stays out: the
    #: odometry runs without the ground and its pitch drift shows in the height over a lag.
    odo_pair_lags: tuple[int, ...] = (10, 30)
    odo_pair_t_a: tuple[float, float] = (0.02, 0.006)
    odo_pair_t_b: tuple[float, float] = (0.0002, 0.0002)
    #: The pairs' heading, sigma ``a + b * lag`` (rad), shared as the positions are, at
    #: least the heading hat's measure of the odometry's heading error scaled to the lag
    #: (:func:`_odometry_pairs`): a scan-to-map registration's heading over 10 and 30
    #: frames is good to 5-20 mdeg on dense and sparse scenes alike (RMS over nine
    #: seeds-20 matrix cells: 5-18 and 7-20 mdeg; 45-53 on a sparse hard one), nearly as
    #: good over 30 frames as over 10, where the gyros' integral drifts with their bias.
    #: C2 anchor error with / without (fused alone): tight_curve-f100-d0.3-osdar23-s20
    #: 3.47 / 4.47 px, fire_site-f100-d1-hard-s20 2.57 / 3.28,
    #: klein_flottbek-f60-d0.3-hard-s20 2.41 / 2.59, fire_site-f60-d1-osdar23-s20 0.79 /
    #: 0.63. 0 leaves it out.
    odo_pair_r_a: float = 0.01 * DEG
    odo_pair_r_b: float = 0.0002 * DEG
    #: The pairs' along-track sigma may be scaled down to this share of its design by
    #: their own residuals (:func:`variance_factors`; every other block's factor stays
    #: >= 1): the design's 2 cm is what a degenerate scene's registration slips, and on a
    #: scene it holds KISS-ICP's pairs are good to 4-6 mm, where the INS velocity's
    #: integral (0.02 m/s of white noise a record) strays 1.1 cm over 30 frames; at the
    #: design sigma the velocity won (tight_curve-f60-d1-osdar23-s20-bogies: fused 1.74x
    #: the odometry's translation error over 30 frames, 1.09x scaled).
    odo_pair_along_floor: float = 0.25
    #: Fine scan-to-scan registration (:mod:`~worker.preparation.localization.scan_pairs`)
    #: of the odometry pairs: their lateral component where its own sigma (floored at
    #: ``scan_pair_lat_floor``, m) is sharper than KISS-ICP's pair. The preparation
    #: option ``fused_scan_pairs: false`` (``PrepareConfig.localization.options``) turns
    #: it off: on fire_site 100 frames at full density the pairs cost 7 s (preparation 1.79
    #: -> 2.42x KISS-ICP alone). Measured on 12 matrix cells (docs/method.md): the C2
    #: anchor jitter p90 lower in 10, e.g. a slow sparse station 3.41 -> 1.18 px.
    scan_pairs: bool = True
    scan_pair_lat_floor: float = 0.002
    #: A lag longer than the sequence is replaced by the pair over its whole length (lag
    #: n - 1, at least :data:`MIN_WHOLE_RUN_LAG`): without it a 10-frame run had no
    #: lateral reference beyond KISS-ICP's steps, and the gyros' heading noise, carried
    #: sideways by the rail motion, moved the poses across the track (the C2 anchor error
    #: of station-f10-d1-good-s10 1.28 -> 0.11 px, klein_flottbek-f10-d1-hard-s11 1.69 ->
    #: 0.53), and a 20-frame run had only the lag-10 pairs. Not on a run degenerate
    #: along the track: there a registration's lateral moves with where it starts along
    #: the track, and KISS-ICP's, the first frames mapped (:func:`_map_first_steps`) and
    #: the fine registration were each 8-16 mm off over 9 frames somewhere (straight_sparse
    #: cells and seeds), against 5 without the pair.
    odo_pair_whole_run: bool = True
    #: KISS-ICP's first steps re-registered against the map of the frames after them
    #: (:func:`_map_first_steps`; the option ``fused_map_first_steps: 0`` turns it off).
    map_first_steps: int = 3
    map_first_frames: int = 8
    #: The merged cloud's yaw against the base (:mod:`.lidar_yaw`), estimated from the scan
    #: pairs on straight track and taken out of every lidar-derived relative pose (the
    #: steps and the pairs). The option ``fused_lidar_yaw: false`` turns it off.
    lidar_yaw: bool = True
    #: The merged cloud's pitch against the base (:func:`.lidar_yaw.lidar_pitch_offset`),
    #: from the ground pairs on a near-constant grade, taken out of the same relative poses
    #: and the ground pairs (the lidar alignment brings the lidars onto one reference, whose
    #: own pitch stays: 1 mrad climbed 0.5 mm a frame, 50 mm over 100 frames). The option
    #: ``fused_lidar_pitch: false`` turns it off.
    lidar_pitch: bool = True
    #: Share of an odometry step's variance that adds up over steps as a random walk in
    #: the solution's information (the pose covariance behind the placement bound); the
    #: rest is the per-scan registration error, which does not add up (:mod:`.scan_errors`;
    #: 1: independent steps).
    odo_drift_share: float = 0.25
    #: Estimate the INS wander from the whole solution (:func:`wander_factors`).
    estimate_wander: bool = True
    #: Estimate the rotation smoothness per axis from the solution (:func:`motion_factors`).
    estimate_motion: bool = True
    #: Variance factors from redundancy numbers (:func:`variance_factors`).
    redundancy_vce: bool = True
    att_bias: float = 1.0 * DEG
    pos_bias: float = 2.0
    att_bias_step: tuple[float, float, float] = (0.01 * DEG, 0.1 * DEG, 1.0 * DEG)
    pos_bias_step: tuple[float, float, float] = (0.02, 0.1, 1.0)  # floor, default, cap
    #: Where the odometry is degenerate along the track, the INS positions' wander is
    #: measured against the INS velocity (:func:`_position_wander_against_velocity`);
    #: False keeps the floor.
    ins_p_wander_from_velocity: bool = True
    #: The gyros' frame-to-frame rotation (:mod:`.gyro`, ``novatel_oem7_corrimu``), sigma
    #: per axis (rad): a tactical-grade IMU's angle noise over 0.1 s is under 1 mdeg; the
    #: block's variance factor takes what a worse IMU or the interpolation to the lidar
    #: times adds. The option ``fused_gyro: false`` turns it off.
    gyro: bool = True
    gyro_r: float = 0.001 * DEG
    #: Prior sigma of the gyros' constant bias (rad/s, base axes), estimated with the
    #: poses: a tactical-grade IMU's residual bias is degrees per hour (5 deg/h: 14 mdeg
    #: over a 10 s sequence, 1.8 px at 50 m on rgb_highres_center). The heading's bias
    #: has no reference but the lidar's lateral motion; with a looser prior (10 deg/h) it
    #: took up the merged cloud's errors on some matrix cells (station-f100-d1-osdar23-s1:
    #: the anchor error 0.54 -> 2.4 px; 1.3 px at 5 deg/h).
    gyro_bias: float = 5.0 * DEG / 3600.0
    #: A rail vehicle's base moves along its own axis (:func:`_rail_motion`): frame k + 1's
    #: lateral position in frame k is the chord of the turn between them plus the turn
    #: times the base's distance ahead of the bogies' midpoint (a state), plus the
    #: change of the body's sway (per-frame offset states), within this sigma per step
    #: (m): what the rails' irregularities and the model's linearisation leave.
    #: The option ``fused_rail_motion: false`` turns it off.
    rail_motion: bool = True
    rail_motion_lat: float = 0.001
    #: The same vertically: frame k + 1's height in frame k is the chord of the pitch
    #: between them (the body follows the track's grade) plus the change of its bounce,
    #: within this sigma per step (m); 0 turns it off.
    rail_motion_vert: float = 0.001
    #: The body's sway and bounce on its suspension: per-frame offsets (lateral,
    #: vertical, m) from the rail-following path and their rates, a damped oscillator per
    #: axis (:mod:`.body_sway`) with this stationary sd (a few mm; the wheels' play in the
    #: gauge adds as much sideways) ...
    sway: tuple[float, float] = (0.005, 0.005)
    #: ... this natural frequency (Hz; a carbody's lateral and bounce modes are near
    #: 0.5-1.5 Hz) ...
    sway_hz: tuple[float, float] = (1.0, 1.0)
    #: ... and this damping ratio (well damped: the prior spreads over a band of
    #: frequencies, not one). The offset then changes by up to 7 mm (1 sigma) within half a
    #: second, as a smooth sway does, where independent per-frame steps bounded by an
    #: offset prior allowed 4 mm.
    sway_damping: float = 0.5
    #: Prior sigma of the base's distance ahead of the bogies' midpoint (m; a state of
    #: the solve, at 0 a priori), in the lateral and the vertical rail motion. A base far
    #: ahead of its bogies (an OSDaR23 base at the train's front: 5-10 m) moves sideways
    #: by it times the turn and vertically by it times the change of grade: pinned at 0,
    #: a 60-frame tight curve with the base 12.5 m ahead had its fused heights 1.3 cm
    #: low over 30 frames and its C2 anchor error 1.90 px (0.73 estimated). Estimated
    #: only on a run that travels :data:`BOGIE_MIN_TRAVEL_M` with an odometry not
    #: degenerate: on a slow short curve whose odometry misses the turn it traded against
    #: the turn (test_fused_heading.py: 0.008 -> 0.16 deg over 10 frames).
    bogie_offset: float = 10.0
    #: Prior sigma of the merged cloud's residual pitch against the base (rad), estimated
    #: with the poses (after :func:`~.lidar_yaw.lidar_pitch_offset`'s, applied where it
    #: is significant): a cloud pitched by p gives every lidar step and ground pair a climb
    #: of p per metre, which the rail motion (the base moves along its own axis) and the
    #: INS tell from a grade. Beside the body's bounce the estimate before the solve was
    #: not significant at 0.8 +- 0.45 mrad on station-f100-d1-osdar23-s11 (a 50 mm climb
    #: over 60 m, 6 px).
    cloud_pitch: float = 1e-3
    #: Prior sigma (rad per metre) of the ground pairs' roll drift, a state of the solve:
    #: where the merged cloud's lidars disagree by hundredths of a degree (OSDaR23's
    #: clouds are merged from six lidars, each with its own calibration), the ground a
    #: pair's two frames share comes from different lidars in each, and the pair's roll is
    #: off in proportion to the distance between its frames (straight_sparse-f60-d0.3-
    #: osdar23-s11: +6.5 mdeg a 1.1 m step, +68 over ten; none with the lidars merged
    #: without error). The gyros tell it from the track's own roll (a cant). A pitch drift
    #: of every pair, freed the same way, traded against the odometry's and the rail
    #: motion's pitch in curves (tight_curve-f20-d1-osdar23-s11: anchor error 1.09 ->
    #: 2.91 px): only the longer pairs' pitch has one (``ground_pitch_drift``). 0 turns
    #: the state off.
    ground_tilt: float = 2e-4
    #: Prior sigma (rad per metre) of the pitch drift of the ground pairs longer than the
    #: shortest lag (the lag-10 pairs), a state of the solve: their pitch is off in
    #: proportion to the distance between their frames by more than the chain of lag-1
    #: pairs over the same frames (straight_sparse-f60-d0.3-osdar23-s11: +9.7 mdeg a 20 m
    #: pair against ten lag-1 pairs' +5.9; straight_sparse-f100-d0.3-hard-s11, merged
    #: without error, +6.0 against +3.2), and the solve followed them (the pitch drifted
    #: 49 mdeg over 59 frames there, anchor 6.2 px). With the state the lag-1 pairs and
    #: the gyros hold the pitch rate while the lag-10 pairs keep telling its changes
    #: (6.2 -> 2.9 px). The lag-1 pairs keep no such state: freed, a pitch drift of every
    #: pair traded against the odometry's and the rail motion's pitch in curves (see
    #: ``ground_tilt``). 0 turns it off.
    ground_pitch_drift: float = 2e-4
    #: The INS's accelerometers (:mod:`.accelerometer`): the second differences of the
    #: positions they see, sigma (along, lateral, vertical, m) per stencil: a
    #: tactical-grade accelerometer's velocity noise over 0.1 s is a few tenths of a
    #: millimetre a second, a hundredth of these; they take the lever arm's share (the
    #: body's rotation sway at the INS's offset) and the interpolation to the lidar
    #: times. The option ``fused_accel: false`` turns it off.
    accel: bool = True
    accel_diff: tuple[float, float, float] = (0.0005, 0.0002, 0.0002)
    #: Their bias (m/s^2, base axes), estimated with the poses, linear between knots
    #: ``accel_bias_knot_s`` apart: the accelerometers' own residual bias and the gravity
    #: the INS's attitude error leaves in (0.15 deg: 2.6 mg). Prior on its size (3 mg, a
    #: tactical-grade IMU's bias with that gravity) and on its change between knots.
    accel_bias: float = 0.03
    accel_bias_step: float = 0.01
    accel_bias_knot_s: float = 2.0


_ONES = np.ones(1)


@dataclass
class Problem:
    """Everything the residual function needs (fixed during a solve)."""

    R0: F64  # (n, 3, 3) initial rotations
    p0: F64  # (n, 3) initial positions
    d_t: F64  # (n-1, 3) odometry translations in the earlier frame
    d_R: F64  # (n-1, 3, 3) odometry rotations
    w_odo_t: F64  # (n-1, 3) 1/sigma per component
    w_odo_r: F64  # (n-1, 3) 1/sigma about roll, pitch, heading
    ins_k: NDArray[np.int64]  # frames with an INS record
    p_ins: F64  # (m, 3) nominal INS positions (jumps removed)
    R_ins: F64  # (m, 3, 3) nominal INS rotations
    w_ins: F64  # (m, 3) angular rate (world, rad/s)
    rail: dict | None  # linearised rail constraint or None
    sig: Sigmas
    n: int
    lever_sigma: F64  # (3,) prior sigmas of the lever arm (x tight unless observable)
    bore_sigma: float  # prior sigma of the boresight (tight without rails)
    knot_i: NDArray[np.int64]  # (m,) left bias knot of each INS record
    knot_a: F64  # (m,) interpolation weight of the right knot
    n_knots: int  # number of INS bias knots (>= 1)
    bias_sigma: F64  # (6,) prior sigmas of a knot's size (attitude rad, position m)
    bias_step_sigma: F64  # (6,) prior sigmas of its change between knots
    #: (3, 3) the axes of the attitude bias in the world: forward along the sequence's
    #: mean heading, left, up (about them roll, pitch and heading wander at their own rates)
    R_bias: F64 = field(default_factory=lambda: np.eye(3))
    ground: dict | None = None  # ground pairs: k, j (P,), T_k_j (P, 4, 4), w (P, 3)
    #: INS velocity steps: k (S,) earlier frames, dp (S, 3) the step's world
    #: displacement from the INS velocity, w (S,) 1/sigma (:func:`_velocity_steps`)
    vel: dict | None = None
    #: Odometry pairs: k, j (Q,), T_k_j (Q, 4, 4), w (Q, 2): 1/sigma of frame j's
    #: position in frame k along the track and laterally (:func:`_odometry_pairs`)
    odo_pairs: dict | None = None
    #: Gyro steps: D (n-1, 3, 3) the base's rotation from frame k to k + 1, w (n-1, 3)
    #: 1/sigma (0: no gyro there) (:func:`_gyro_steps`)
    gyro: dict | None = None
    #: Rail motion: w (n-1,) 1/sigma of each step's lateral motion, d the base's distance
    #: ahead of the bogies' midpoint (m) (:func:`_rail_motion`)
    nh: dict | None = None
    #: Accelerometer jerks: meas (n-3, 3) the third differences of the positions (base
    #: axes of each stencil's second frame), w (n-3, 3) 1/sigma (:mod:`.accelerometer`)
    accel: dict | None = None
    #: Variance factors of the measurement blocks (:data:`SCALED_BLOCKS`), per component:
    #: each block's sigmas are multiplied by these (:func:`variance_factors`).
    scale: dict[str, F64] = field(default_factory=dict)
    #: (n-1,) steps replaced by a zero-velocity update (never rescaled)
    zupt: NDArray[np.bool_] = field(default_factory=lambda: np.zeros(0, dtype=bool))
    #: (m, 3) factor on the INS attitude sigma per record and axis
    #: (:func:`_ins_attitude_factors`; None: 1)
    ins_r_share: F64 | None = None
    #: (n-2, 3) and (n-3, 4) weights of the second and third differences of the positions
    #: at the frames' times (:func:`difference_weights`: 1 -2 1 and -1 3 -3 1 for even
    #: steps; a dropped frame's longer step is accounted for)
    #: (key, Jacobian sparsity) cached by :func:`_cached_sparsity`
    structure: tuple[Any, csc_matrix] | None = None
    #: (3,) the INS attitude's white noise (rad) the attitude sigmas were built from
    #: (:func:`_ins_attitude_white`; None: ``sig.ins_r``)
    ins_white: F64 | None = None
    diff2: F64 = field(default_factory=lambda: np.zeros((0, 3)))
    diff3: F64 = field(default_factory=lambda: np.zeros((0, 4)))
    #: Accelerometer bias knots (3 parameters each, after the gyro bias; 0 without the
    #: accelerometer block) and, per second-difference row, its left knot and the right
    #: knot's weight at the row's middle time
    n_acc_knots: int = 0
    acc_knot_i: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    acc_knot_a: F64 = field(default_factory=lambda: np.zeros(0))

    def s(self, block: str) -> F64:
        """The variance factor(s) of ``block`` (ones until estimated)."""
        return self.scale.get(block, _ONES)

    def s_odo(self, block: str) -> F64:
        """(n-1, 3) variance factors of the odometry rows (1 on zero-velocity steps)."""
        f = np.broadcast_to(self.s(block), (self.n - 1, 3)).copy()
        if len(self.zupt):
            f[self.zupt] = 1.0
        return f


def _log_rotation(R: F64) -> F64:
    """(n, 3) rotation vectors of rotation matrices (n, 3, 3), accurate at small angles.

    The residuals take this many times per Jacobian (scipy's ``from_matrix`` orthonormalises
    and checks every matrix and was a fifth of the smoothing's time). Angles above 3 rad
    (never a residual here, but possible in principle) go through scipy.
    """
    v = 0.5 * np.stack(
        [R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]], axis=1
    )
    s = np.linalg.norm(v, axis=1)
    c = 0.5 * (np.trace(R, axis1=1, axis2=2) - 1.0)
    theta = np.arctan2(s, c)
    small = s < 1e-12
    scale = np.where(small, 1.0, theta / np.where(small, 1.0, s))
    out = v * scale[:, None]
    big = theta > 3.0
    if np.any(big):
        out[big] = Rotation.from_matrix(R[big]).as_rotvec()
    return out


def _rotvec_rates(R: F64, times: F64) -> F64:
    """(n, 3) world angular rates from rotations (n, 3, 3) by central differences."""
    n = len(R)
    if n < 2:
        return np.zeros((n, 3))
    rot = Rotation.from_matrix(R)
    i0 = np.clip(np.arange(n) - 1, 0, n - 1)
    i1 = np.clip(np.arange(n) + 1, 0, n - 1)
    dt = times[i1] - times[i0]
    dt[dt <= 0] = 1.0
    return (rot[i1] * rot[i0].inv()).as_rotvec() / dt[:, None]


def difference_weights(times: F64, order: int) -> F64:
    """(n - order, order + 1) weights w with sum_j w_j p_(k+j) = order! * h^order times
    the divided difference of p over times k .. k + order (h: the median step): the
    usual 1 -2 1 / -1 3 -3 1 stencils for even steps, exact for polynomials of lower
    degree whatever the steps (Lagrange form of divided differences)."""
    t = np.asarray(times, dtype=np.float64)
    n = len(t)
    if n <= order:
        return np.zeros((0, order + 1))
    h = float(np.median(np.diff(t)))
    h = h if h > 0 else 1.0
    out = np.empty((n - order, order + 1))
    for j in range(order + 1):
        prod = np.ones(n - order)
        for m in range(order + 1):
            if m != j:
                prod *= t[j : n - order + j] - t[m : n - order + m]
        out[:, j] = math.factorial(order) * h**order / prod
    return out


def _linearise_rails(ego, p_world: F64, R_hint: F64, sig: Sigmas) -> dict:
    """Centreline frames at the projections of ``p_world`` (flipped to face like R_hint)
    and the orientation sigmas (3,) rad there (floor, or the centreline's own noise)."""
    T, s, _ = rail_frames(ego, p_world)
    cos = np.einsum("ni,ni->n", R_hint[:, :, 0], T[:, :3, 0])
    if np.median(cos) < 0.0:
        T[:, :3, :3] = T[:, :3, :3] @ np.diag([-1.0, -1.0, 1.0])
    noise = orientation_noise(ego, float(np.min(s)), float(np.max(s))) if len(s) else np.zeros(3)
    sigma_r = np.maximum(np.asarray(sig.rail_r, dtype=np.float64), noise)
    if len(s) and float(np.ptp(s)) >= RAIL_HEADING_BASELINE_M:
        sigma_r[2] = max(sigma_r[2], sig.rail_heading_moving)
    # Frames within one correlation length of track share one centreline error: together
    # they carry one orientation measurement, not one each (else a slow or short sequence
    # pins its relative rotations to the fitted curve's wiggles).
    sharing = _frames_sharing(s, RAIL_CORRELATION_M)
    return {
        "c": T[:, :3, 3].copy(),
        "R": T[:, :3, :3].copy(),
        "sigma_r": sigma_r[None, :] * np.sqrt(sharing)[:, None],
        "sigma_r_base": sigma_r,
        "frames_sharing": float(np.median(sharing)),
    }


def _frames_sharing(s: F64, length_m: float) -> F64:
    """(n,) how many frames lie within ``length_m / 2`` of each frame along the track."""
    order = np.sort(s)
    lo = np.searchsorted(order, s - 0.5 * length_m, side="left")
    hi = np.searchsorted(order, s + 0.5 * length_m, side="right")
    return np.maximum(hi - lo, 1).astype(np.float64)


def _n_params(n: int, n_knots: int, n_acc_knots: int = 0) -> int:
    """Length of the parameter vector without :func:`_extra_cols`: poses, misalignment, INS
    bias knots, gyro bias, accelerometer bias knots."""
    return 6 * n + 7 + 6 * n_knots + 3 + 3 * n_acc_knots


def _extra_cols(pb: Problem) -> dict[str, int]:
    """First column of each block after :func:`_n_params`'s, and "end" (the length of the
    parameter vector): with the rail motion the body's sway offsets ("sway": frame k's
    lateral, vertical at + 2 k, + 2 k + 1), their rates ("sway_rate", the same layout)
    and the base's distance ahead of the bogies' midpoint ("bogie"); with the ground pairs
    the cloud's residual pitch ("cloud_pitch"), the pairs' roll drift per metre
    ("ground_tilt") and the longer pairs' pitch drift per metre ("ground_pitch")."""
    i = _n_params(pb.n, pb.n_knots, pb.n_acc_knots)
    out = {}
    if pb.nh is not None:
        out["sway"], out["sway_rate"], out["bogie"] = i, i + 2 * pb.n, i + 4 * pb.n
        i += 4 * pb.n + 1
    if pb.ground is not None:
        out["cloud_pitch"] = i
        i += 1
        if pb.sig.ground_tilt > 0:
            out["ground_tilt"] = i
            i += 1
        if pb.sig.ground_pitch_drift > 0:
            out["ground_pitch"] = i
            i += 1
    out["end"] = i
    return out


def n_params(pb: Problem) -> int:
    """Length of ``pb``'s parameter vector."""
    return _extra_cols(pb)["end"]


def _sway_of(x: F64, pb: Problem) -> tuple[F64, float]:
    """(n, 2) the body's sway offsets (lateral, vertical, m) and the base's distance ahead
    of the bogies' midpoint (m)."""
    cols = _extra_cols(pb)
    i0 = cols["sway"]
    return x[i0 : i0 + 2 * pb.n].reshape(pb.n, 2), float(x[cols["bogie"]])


def _sway_rate_of(x: F64, pb: Problem) -> F64:
    """(n, 2) the rates of the body's sway offsets (lateral, vertical, m/s)."""
    i0 = _extra_cols(pb)["sway_rate"]
    return x[i0 : i0 + 2 * pb.n].reshape(pb.n, 2)


def _cloud_pitch_of(x: F64, pb: Problem) -> float:
    """The merged cloud's residual pitch against the base (rad; 0 without ground pairs)."""
    i = _extra_cols(pb).get("cloud_pitch")
    return 0.0 if i is None else float(x[i])


def _ground_tilt_of(x: F64, pb: Problem) -> float:
    """The ground pairs' roll drift per metre between their frames (rad/m; 0 without the
    state)."""
    i = _extra_cols(pb).get("ground_tilt")
    return 0.0 if i is None else float(x[i])


def _ground_pitch_drift_of(x: F64, pb: Problem) -> float:
    """The longer ground pairs' pitch drift per metre between their frames (rad/m; 0
    without the state)."""
    i = _extra_cols(pb).get("ground_pitch")
    return 0.0 if i is None else float(x[i])


def _tilted(t: F64, pitch: float, along: F64 | None = None) -> F64:
    """(m, 3) translations measured in a cloud pitched by ``pitch`` (rad, about the base y
    axis; small) expressed in the base: :func:`~.lidar_yaw.tilt_lidar_poses` to first
    order, the climb ``pitch`` times ``along`` (m,) (default the translations' own x: the
    solve passes its poses' own, as KISS-ICP's is unreliable on a degenerate straight)."""
    x = t[:, 0] if along is None else along
    return t + pitch * np.column_stack([t[:, 2], np.zeros(len(t)), -x])


def _acc_bias_col(n: int, n_knots: int) -> int:
    """First column of the accelerometers' bias knots (3 each: m/s^2, base axes)."""
    return 6 * n + 7 + 6 * n_knots + 3


def _gyro_bias_col(n: int, n_knots: int) -> int:
    """First column of the gyros' bias (3: rad/s about the base axes)."""
    return 6 * n + 7 + 6 * n_knots


def _unpack(x: F64, pb: Problem) -> tuple[F64, F64, F64, F64, float]:
    n = pb.n
    xp = x[: 6 * n].reshape(n, 6)
    R = Rotation.from_rotvec(xp[:, :3]).as_matrix() @ pb.R0
    p = pb.p0 + xp[:, 3:]
    return (R, p, *_misalignment_of(x, pb))


def _misalignment_of(x: F64, pb: Problem) -> tuple[F64, F64, float]:
    """The misalignment part of ``x``: lever (3,), boresight (3,), latency."""
    n = pb.n
    return x[6 * n : 6 * n + 3], x[6 * n + 3 : 6 * n + 6], float(x[6 * n + 6])


def _bias_knots_of(x: F64, pb: Problem) -> F64:
    """(n_knots, 6) INS bias knots: attitude (world rotation vector, rad), position (m)."""
    i0 = 6 * pb.n + 7
    return x[i0 : i0 + 6 * pb.n_knots].reshape(pb.n_knots, 6)


def _bias_at_records(x: F64, pb: Problem) -> F64:
    """(m, 6) INS bias at each INS record, linear between its knots."""
    knots = _bias_knots_of(x, pb)
    b = (1.0 - pb.knot_a)[:, None] * knots[pb.knot_i]
    if pb.n_knots > 1:
        b = b + pb.knot_a[:, None] * knots[np.minimum(pb.knot_i + 1, pb.n_knots - 1)]
    return b


def _bias_knots(times: F64, k: NDArray[np.int64], knot_s: float) -> tuple:
    """Knots ``knot_s`` apart (at least 2 over the span, or 1 for a single record) and, per
    INS record at frames ``k``, its left knot and the right knot's linear weight."""
    t = times[k] if len(k) else times[:1]
    t0, t1 = float(np.min(t)), float(np.max(t))
    span = t1 - t0
    if span <= 0.0:
        return np.zeros(len(k), dtype=np.int64), np.zeros(len(k)), 1
    n_knots = max(2, int(np.ceil(span / knot_s)) + 1)
    u = (times[k] - t0) / span * (n_knots - 1)
    i = np.clip(np.floor(u).astype(np.int64), 0, n_knots - 2)
    return i, u - i, n_knots


def residuals(x: F64, pb: Problem, same_poses: tuple[F64, F64, F64] | None = None) -> F64:
    """All residual blocks, stacked (see the module docstring).

    ``same_poses`` = (R, p, r) of a parameter vector with the same pose part as ``x``:
    then only the blocks of the misalignment, the INS bias and the gyro bias (the INS
    and gyro residuals and the priors) are computed, the others copied from ``r`` (the
    Jacobian's columns of those parameters; the same values as a full evaluation).
    """
    if same_poses is not None:
        R, p, r = same_poses
        out_ins, out_prior = _ins_blocks(x, pb, R, p), _prior_blocks(x, pb)
        r = r.copy()
        i0 = 6 * (pb.n - 1)
        r[i0 : i0 + len(out_ins)] = out_ins
        r[len(r) - len(out_prior) :] = out_prior
        if pb.gyro is not None:
            g = _gyro_residuals(x, pb, R)
            i0 = _block_offsets(pb)["gyro"]
            r[i0 : i0 + len(g)] = g
        if pb.accel is not None:
            a = _accel_residuals(x, pb, R, p).ravel()
            i0 = _block_offsets(pb)["accel"]
            r[i0 : i0 + len(a)] = a
        if pb.nh is not None:
            h = _rail_motion_residuals(pb, R, p, x)
            i0 = _block_offsets(pb)["nh"]
            r[i0 : i0 + len(h)] = h
        if pb.vel is not None:
            h = _velocity_residuals(x, pb, R, p)
            i0 = _block_offsets(pb)["ins_v"]
            r[i0 : i0 + len(h)] = h
        if pb.ground is not None:
            h = _ground_residuals(x, pb, R, p)
            i0 = _block_offsets(pb)["ground"]
            r[i0 : i0 + len(h)] = h
            h = _odometry_step_residuals(x, pb, np.swapaxes(R[:-1], 1, 2), p)
            r[: len(h)] = h
        return r
    R, p, _, _, _ = _unpack(x, pb)
    sig = pb.sig
    out = []
    # odometry
    Rt = np.swapaxes(R[:-1], 1, 2)
    out.append(_odometry_step_residuals(x, pb, Rt, p))
    E = np.swapaxes(pb.d_R, 1, 2) @ Rt @ R[1:]
    out.append((_log_rotation(E) * pb.w_odo_r / pb.s_odo("odo_r")).ravel())
    out.append(_ins_blocks(x, pb, R, p))
    # rails
    if pb.rail is not None:
        c, Rr = pb.rail["c"], pb.rail["R"]
        d = p - c
        lat_r = np.einsum("ni,ni->n", d, Rr[:, :, 1]) / (sig.rail_lat * pb.s("rail_lat"))
        ver_r = np.einsum("ni,ni->n", d, Rr[:, :, 2]) / (sig.rail_vert * pb.s("rail_vert"))
        out.append(lat_r)
        out.append(ver_r)
        err = _log_rotation(np.swapaxes(Rr, 1, 2) @ R)
        out.append((err / (pb.rail["sigma_r"] * pb.s("rail_r"))).ravel())
    if pb.ground is not None:
        out.append(_ground_residuals(x, pb, R, p))
    if pb.vel is not None:
        out.append(_velocity_residuals(x, pb, R, p))
    if pb.odo_pairs is not None:
        out.append(_odometry_pair_residuals(pb, R, p).ravel())
    if pb.gyro is not None:
        out.append(_gyro_residuals(x, pb, R))
    if pb.nh is not None:
        out.append(_rail_motion_residuals(pb, R, p, x))
    if pb.accel is not None:
        out.append(_accel_residuals(x, pb, R, p).ravel())
    # smoothness
    if pb.n >= 3:
        c = pb.diff2
        a_world = c[:, :1] * p[:-2] + c[:, 1:2] * p[1:-1] + c[:, 2:] * p[2:]
        a_base = np.einsum("nji,nj->ni", R[1:-1], a_world)
        out.append((a_base / np.asarray(sig.acc)).ravel())
        w = _log_rotation(np.swapaxes(R[:-1], 1, 2) @ R[1:])
        rot_acc = np.asarray(sig.rot_acc) * pb.s("rot_acc")
        out.append(((w[1:] - w[:-1]) / rot_acc).ravel())
    if pb.n >= 4 and sig.jerk is not None:
        c = pb.diff3
        j_world = c[:, :1] * p[:-3] + c[:, 1:2] * p[1:-2] + c[:, 2:3] * p[2:-1] + c[:, 3:] * p[3:]
        j_base = np.einsum("nji,nj->ni", R[1:-2], j_world)
        out.append((j_base / np.asarray(sig.jerk)).ravel())
    out.append(_prior_blocks(x, pb))
    return np.concatenate(out)


def _velocity_residuals(x: F64, pb: Problem, R: F64, p: F64) -> F64:
    """((S) 2,) normalised residuals of the INS velocity steps, along the track and
    sideways: the INS moves with its lever arm, so its displacement over a step is the
    base's plus the turn of the lever, (R_k+1 - R_k) lever (a 3 m lever on a 0.44 deg
    turn over 3 s: 8 mm/s sideways, as much as a sway)."""
    assert pb.vel is not None
    kv = pb.vel["k"]
    lever = _misalignment_of(x, pb)[0]
    d_ins = p[kv + 1] - p[kv] + (R[kv + 1] - R[kv]) @ lever
    miss = d_ins - pb.vel["dp"]
    along = np.einsum("ni,ni->n", R[kv][:, :, 0], miss)
    lat = np.einsum("ni,ni->n", R[kv][:, :, 1], miss)
    both = np.column_stack([along, lat]) * pb.vel["w"][:, None]
    return (both / pb.s("ins_v")).ravel()


def _odometry_step_residuals(x: F64, pb: Problem, Rt: F64, p: F64) -> F64:
    """((n-1) 3,) normalised residuals of the odometry's step translations (measured in
    the cloud: tilted by its residual pitch); Rt (n-1, 3, 3) the earlier frames' R^T."""
    B = np.einsum("nij,nj->ni", Rt, p[1:] - p[:-1])
    dp = B - _tilted(pb.d_t, _cloud_pitch_of(x, pb), B[:, 0])
    return (dp * pb.w_odo_t / pb.s_odo("odo_t")).ravel()


def _ground_residuals(x: F64, pb: Problem, R: F64, p: F64) -> F64:
    """((P) 3,) normalised residuals of the ground pairs: the height, roll and pitch of frame
    j in frame k (the measured translation tilted by the cloud's residual pitch)."""
    assert pb.ground is not None
    g = pb.ground
    Rk, Rj = R[g["k"]], R[g["j"]]
    MRt = np.swapaxes(g["T_k_j"][:, :3, :3], 1, 2)
    B_t = np.einsum("nji,nj->ni", Rk, p[g["j"]] - p[g["k"]])
    t = _tilted(g["T_k_j"][:, :3, 3], _cloud_pitch_of(x, pb), B_t[:, 0])
    E_t = np.einsum("nij,nj->ni", MRt, B_t - t)
    E_r = _log_rotation(MRt @ np.swapaxes(Rk, 1, 2) @ Rj)
    E_r[:, 0] += B_t[:, 0] * _ground_tilt_of(x, pb)  # measured = true + drift
    E_r[:, 1] += g["long"] * B_t[:, 0] * _ground_pitch_drift_of(x, pb)
    gr = np.column_stack([E_t[:, 2], E_r[:, 0], E_r[:, 1]]) * g["w"] / pb.s("ground")
    return gr.ravel()


def _gyro_residuals(x: F64, pb: Problem, R: F64) -> F64:
    """((n-1) 3,) normalised residuals of the gyro steps: the gyros measure D Exp(b dt),
    their constant bias b turning each step by b dt."""
    assert pb.gyro is not None
    i0 = _gyro_bias_col(pb.n, pb.n_knots)
    b_dt = x[i0 : i0 + 3][None, :] * pb.gyro["dt"][:, None]
    D_true = pb.gyro["D"] @ Rotation.from_rotvec(-b_dt).as_matrix()
    E = np.swapaxes(D_true, 1, 2) @ np.swapaxes(R[:-1], 1, 2) @ R[1:]
    return (_log_rotation(E) * pb.gyro["w"] / pb.s("gyro")).ravel()


def _ins_blocks(x: F64, pb: Problem, R: F64, p: F64) -> F64:
    """The INS residuals (positions, attitudes) for poses ``R`` (n, 3, 3), ``p`` (n, 3)."""
    lever, bore, lat = _misalignment_of(x, pb)
    sig = pb.sig
    out: list[F64] = []
    k = pb.ins_k
    if len(k):
        # The latency is not applied to positions: it moves them along the track only,
        # exactly like the along-track lever arm and the INS's own along-track error, none
        # of which anything here observes (see the module docstring).
        # INS = truth + slow bias: position p + b(t), attitude Exp(beta(t)) @ R.
        bias = _bias_at_records(x, pb)
        beta = bias[:, :3] @ pb.R_bias.T  # world rotation vectors
        pred = p[k] + R[k] @ lever + bias[:, 3:]
        out.append(((pred - pb.p_ins) / (sig.ins_p * pb.s("ins_p"))).ravel())
        R_meas = Rotation.from_rotvec(pb.w_ins * lat).as_matrix() @ pb.R_ins
        R_pred = (
            Rotation.from_rotvec(beta).as_matrix() @ R[k] @ Rotation.from_rotvec(bore).as_matrix()
        )
        err = _log_rotation(np.swapaxes(R_meas, 1, 2) @ R_pred)
        share = 1.0 if pb.ins_r_share is None else pb.ins_r_share
        out.append((err / (sig.ins_r * share * pb.s("ins_r"))).ravel())
    return np.concatenate(out) if out else np.zeros(0)


def _prior_blocks(x: F64, pb: Problem) -> F64:
    """The priors of the misalignment, the gyro and accelerometer biases, the body's sway
    and bogie offset, the cloud's pitch and the ground pairs' drifts, then of the INS bias
    knots and, last of all rows, their steps (:func:`wander_factors` reads them there)."""
    lever, bore, lat = _misalignment_of(x, pb)
    sig = pb.sig
    out: list[F64] = []
    out.append(lever / pb.lever_sigma)
    out.append(bore / pb.bore_sigma)
    out.append(np.array([lat / sig.latency]))
    i0 = _gyro_bias_col(pb.n, pb.n_knots)
    out.append(x[i0 : i0 + 3] / sig.gyro_bias)
    if pb.n_acc_knots:
        acc = _acc_bias_knots_of(x, pb)
        out.append((acc / sig.accel_bias).ravel())
        out.append((np.diff(acc, axis=0) / sig.accel_bias_step).ravel())
    if pb.nh is not None:
        o, d = _sway_of(x, pb)
        v = _sway_rate_of(x, pb)
        for c, prior in enumerate(pb.nh["sway"]):  # first frame's two rows, each step's two
            out.append(prior.residuals(np.column_stack([o[:, c], v[:, c]])))
        out.append(np.array([d / pb.nh["bogie_sigma"]]))
    if pb.ground is not None:
        out.append(np.array([_cloud_pitch_of(x, pb) / sig.cloud_pitch]))
        if sig.ground_tilt > 0:
            out.append(np.array([_ground_tilt_of(x, pb) / sig.ground_tilt]))
        if sig.ground_pitch_drift > 0:
            out.append(np.array([_ground_pitch_drift_of(x, pb) / sig.ground_pitch_drift]))
    knots = _bias_knots_of(x, pb)
    out.append((knots / pb.bias_sigma).ravel())
    out.append((np.diff(knots, axis=0) / pb.bias_step_sigma).ravel())
    return np.concatenate(out)


def _cached_sparsity(pb: Problem) -> csc_matrix:
    """:func:`sparsity`, built once per problem structure (solves and the information
    of one problem share it; building it is ~60 ms of Python for 100 frames)."""
    key = (
        pb.n,
        pb.n_knots,
        pb.rail is None,
        pb.ground is None,
        pb.sig.ground_tilt > 0,
        pb.sig.ground_pitch_drift > 0,
        pb.vel is None,
        None if pb.odo_pairs is None else len(pb.odo_pairs["k"]),
        pb.gyro is None,
        pb.nh is None,
        pb.accel is None,
        pb.n_acc_knots,
    )
    if pb.structure is None or pb.structure[0] != key:
        pb.structure = (key, sparsity(pb))
    return pb.structure[1]


def sparsity(pb: Problem) -> csc_matrix:
    """Jacobian sparsity pattern matching :func:`residuals`' row order."""
    n = pb.n
    m_cols = n_params(pb)
    extra = _extra_cols(pb)
    rows: list[tuple[int, list[int]]] = []
    mis = list(range(6 * n, 6 * n + 7))

    def frame_cols(k: int) -> list[int]:
        return list(range(6 * k, 6 * k + 6))

    def knot_cols(j: int) -> list[int]:
        return list(range(6 * n + 7 + 6 * j, 6 * n + 13 + 6 * j))

    def bias_cols(i: int) -> list[int]:
        """The bias knots an INS record (index i into ins_k) depends on."""
        j = int(pb.knot_i[i])
        return knot_cols(j) + (knot_cols(j + 1) if j + 1 < pb.n_knots else [])

    r = 0
    tilt = [extra["cloud_pitch"]] if "cloud_pitch" in extra else []
    for block in range(2):  # odometry translation (with the cloud's pitch), rotation
        for k in range(n - 1):
            for _ in range(3):
                rows.append((r, frame_cols(k) + frame_cols(k + 1) + (tilt if block == 0 else [])))
                r += 1
    for block in range(2):  # INS position, attitude
        del block
        for i, k in enumerate(pb.ins_k):
            for _ in range(3):
                rows.append((r, frame_cols(int(k)) + mis + bias_cols(i)))
                r += 1
    if pb.rail is not None:
        for _ in range(2):
            for k in range(n):
                rows.append((r, frame_cols(k)))
                r += 1
        for k in range(n):
            for _ in range(3):
                rows.append((r, frame_cols(k)))
                r += 1
    if pb.ground is not None:
        for k, j, long in zip(pb.ground["k"], pb.ground["j"], pb.ground["long"], strict=True):
            for c in range(3):
                if c == 0:
                    tilt = [extra["cloud_pitch"]]
                elif c == 1:  # roll with its drift
                    tilt = [extra["ground_tilt"]] if "ground_tilt" in extra else []
                else:  # pitch, the longer pairs' with theirs
                    tilt = [extra["ground_pitch"]] if long and "ground_pitch" in extra else []
                rows.append((r, frame_cols(int(k)) + frame_cols(int(j)) + tilt))
                r += 1
    if pb.vel is not None:  # with the lever arm
        for k in pb.vel["k"]:
            for _ in range(2):
                rows.append((r, frame_cols(int(k)) + frame_cols(int(k) + 1) + mis[:3]))
                r += 1
    if pb.odo_pairs is not None:
        for k, j in zip(pb.odo_pairs["k"], pb.odo_pairs["j"], strict=True):
            for _ in range(ODO_PAIR_COMPONENTS):
                rows.append((r, frame_cols(int(k)) + frame_cols(int(j))))
                r += 1
    gyro_bias = list(range(_gyro_bias_col(n, pb.n_knots), _acc_bias_col(n, pb.n_knots)))
    a0 = _acc_bias_col(n, pb.n_knots)

    def acc_cols(j: int) -> list[int]:
        return list(range(a0 + 3 * j, a0 + 3 * j + 3))

    if pb.gyro is not None:
        for k in range(n - 1):
            for _ in range(3):
                rows.append((r, frame_cols(k) + frame_cols(k + 1) + gyro_bias))
                r += 1
    s0 = extra.get("sway", 0)
    if pb.nh is not None:
        for k in range(n - 1):
            for c in range(2):
                cols = frame_cols(k) + frame_cols(k + 1) + [s0 + 2 * k + c, s0 + 2 * k + 2 + c]
                rows.append((r, [*cols, s0 + 4 * n]))  # both rows carry the bogie offset
                r += 1
    if pb.accel is not None:
        for k in range(n - 2):
            j = int(pb.acc_knot_i[k])
            cols = [c for d in range(3) for c in frame_cols(k + d)] + acc_cols(j)
            cols += acc_cols(j + 1) if j + 1 < pb.n_acc_knots else []
            for _ in range(3):
                rows.append((r, cols))
                r += 1
    if n >= 3:
        for _ in range(2):  # position and rotation smoothness
            for k in range(n - 2):
                for _ in range(3):
                    rows.append((r, frame_cols(k) + frame_cols(k + 1) + frame_cols(k + 2)))
                    r += 1
    if n >= 4 and pb.sig.jerk is not None:
        for k in range(n - 3):
            cols = [c for d in range(4) for c in frame_cols(k + d)]
            for _ in range(3):
                rows.append((r, cols))
                r += 1
    for j in range(7):
        rows.append((r, [6 * n + j]))
        r += 1
    for c in gyro_bias:
        rows.append((r, [c]))
        r += 1
    for c in range(a0, a0 + 3 * pb.n_acc_knots):  # accelerometer bias size
        rows.append((r, [c]))
        r += 1
    for j in range(pb.n_acc_knots - 1):  # its change between knots
        for c in range(3):
            rows.append((r, [acc_cols(j)[c], acc_cols(j + 1)[c]]))
            r += 1
    if pb.nh is not None:  # the sway oscillators (per axis: frame 0, each step), bogie
        v0 = s0 + 2 * n
        for c in range(2):
            rows.append((r, [s0 + c]))
            rows.append((r + 1, [v0 + c]))
            r += 2
            for k in range(n - 1):
                cols = [s0 + 2 * k + c, s0 + 2 * k + 2 + c, v0 + 2 * k + c, v0 + 2 * k + 2 + c]
                rows.append((r, cols))
                rows.append((r + 1, cols))
                r += 2
        rows.append((r, [s0 + 4 * n]))
        r += 1
    if pb.ground is not None:
        rows.append((r, [extra["cloud_pitch"]]))
        r += 1
        if "ground_tilt" in extra:
            rows.append((r, [extra["ground_tilt"]]))
            r += 1
        if "ground_pitch" in extra:
            rows.append((r, [extra["ground_pitch"]]))
            r += 1
    for j in range(pb.n_knots):  # bias size
        for c in knot_cols(j):
            rows.append((r, [c]))
            r += 1
    for j in range(pb.n_knots - 1):  # bias change between knots: the last rows
        for c in range(6):
            rows.append((r, [knot_cols(j)[c], knot_cols(j + 1)[c]]))
            r += 1
    ii = np.concatenate([np.full(len(cols), i) for i, cols in rows])
    jj = np.concatenate([np.asarray(cols) for _, cols in rows])
    return coo_matrix((np.ones(len(ii), dtype=int), (ii, jj)), shape=(r, m_cols)).tocsc()


#: A run degenerate along the track keeps its odometry's lateral, vertical, roll and pitch
#: steps at this fraction of their weight.
DEGENERATE_DIVISOR = 3.0


def _odometry_weights(
    inp: LocalizationInput,
    ins: InsFrames,
    d_t: F64,
    d_R: F64,
    health: Health,
    sig: Sigmas,
    heading: HeadingErrors | None = None,
) -> tuple[F64, F64, bool]:
    """1/sigma of the odometry residuals ((n-1, 3) translation and rotation), down-weighted
    where ICP is unreliable; the heading's at most what its measured error over a lag
    (:mod:`.heading_hat`) allows, as a random walk."""
    n1 = len(d_t)
    w_t = np.full((n1, 3), 1.0 / sig.odo_t)
    try:
        run = odometry_run(inp)
        _, odo_health = odometry_track(inp)
    except Exception as exc:
        health.warn(f"fused: odometry unavailable ({exc}); INS and rails only")
        return np.zeros((n1, 3)), np.zeros((n1, 3)), False, None
    degenerate_run = is_degenerate(odo_health)
    deg = degenerate_frames(run)
    along_bad = deg[1:] | deg[:-1]
    # ICP step against the INS speed (INS increments are cm-accurate over one frame).
    speed_ins = np.linalg.norm(ins.v_world, axis=1)
    step_ins = 0.5 * (speed_ins[1:] + speed_ins[:-1]) * np.diff(inp.times)
    slip = np.abs(np.linalg.norm(d_t, axis=1) - step_ins) > 0.3
    along_bad |= slip
    w_t[along_bad, 0] = 1.0 / sig.odo_t_degenerate
    skipped = np.zeros(n1 + 1, dtype=bool)
    skipped[run.skipped] = True
    bad = skipped[1:] | skipped[:-1]
    sigma_r = _odometry_rotation_sigma(inp, d_R, ~bad, health, sig)
    if heading is not None:
        sigma_r[2] = min(max(sigma_r[2], math.sqrt(heading.odometry / heading.lag)), ODO_R_CAP)
        health.metrics["fused_odometry_step_heading_deg"] = math.degrees(sigma_r[2])
    w_r = np.tile(1.0 / sigma_r, (n1, 1))
    if degenerate_run:
        w_t[:, 0] = 1.0 / sig.odo_t_degenerate
        w_t[:, 1:] /= DEGENERATE_DIVISOR
        # the rotations at a third of their weight too, but not the heading where the
        # hat measured it over a lag: a run degenerate along the track (a straight sparse
        # corridor) can hold its heading well (within 0.06 deg over 60 frames; at a third
        # of its weight the fused heading followed an osdar23 INS's turn to 0.3 deg)
        w_r[:, :2] /= DEGENERATE_DIVISOR
        if heading is None:
            w_r[:, 2] /= DEGENERATE_DIVISOR
        health.warn(
            "fused: odometry degenerate along the track; along-track motion from INS and "
            "smoothness only"
        )
    w_t[bad] /= 100.0
    w_r[bad] /= 100.0
    health.metrics["fused_odometry_downweighted_steps"] = float(np.sum(along_bad | bad))
    return w_t, w_r, degenerate_run, sigma_r


#: Longest lag (in bias knot spacings) of the heading hat. At one knot the course's noise
#: (0.07 deg over 10 frames on fire_site) swamped a good INS's and the odometry's heading
#: errors (0.008, 0.024) and the hat put them the wrong way round (fused heading over 30
#: frames 0.015 deg against the INS's 0.008); at three, 0.010.
HEADING_HAT_MAX_KNOTS = 3


def _heading_errors(
    inp: LocalizationInput, ins: InsFrames, health: Health, sig: Sigmas
) -> HeadingErrors | None:
    """The INS's, the odometry's and the course's heading errors over one bias knot
    spacing (:mod:`.heading_hat`), None where they cannot be measured."""
    times = np.asarray(inp.times, dtype=np.float64)
    if len(times) < 2:
        return None
    try:
        T_odo = odometry_track(inp)[0].T
    except Exception:  # the odometry's absence is warned about where it is used
        return None
    dt = float(np.median(np.diff(times)))
    knot = max(1, round(sig.bias_knot_s / dt)) if dt > 0 else 1
    # the longest lag up to HEADING_HAT_MAX_KNOTS knots that leaves enough pairs: the
    # course's noise is the same at every lag, the wander and drift grow with it
    lag = max(knot, min(HEADING_HAT_MAX_KNOTS * knot, len(times) - HEADING_MIN_PAIRS))
    h = heading_errors(
        ins.T_world_base[:, :3, :3], T_odo[:, :3, :3], ins.v_world, times,
        np.asarray(ins.covered, dtype=bool), lag,
    )  # fmt: skip
    if h is not None:
        for name in ("ins", "odometry", "course"):
            v = math.degrees(math.sqrt(getattr(h, name)))
            health.metrics[f"fused_heading_error_{name}_deg"] = v
    return h


#: Ceiling of the odometry's measured rotation step noise (rad).
ODO_R_CAP = 1.0 * DEG


def _odometry_rotation_sigma(
    inp: LocalizationInput, d_R: F64, valid: NDArray[np.bool_], health: Health, sig: Sigmas
) -> F64:
    """(3,) sigma (rad) of an odometry step's rotation about roll, pitch and heading: its
    own step noise (:func:`~.step_noise.step_noise`) within [``sig.odo_r``,
    :data:`ODO_R_CAP`]; ``sig.odo_r`` where it cannot be measured.

    Scan-to-map odometry's steps are the differences of per-scan registration errors: on
    the synthetic scenes 0.010-0.015 deg a step about each axis (0.1 deg about the roll
    axis on a straight track with few structures), where a fixed 0.01 deg made its heading
    outweigh a good INS's (fused heading over 30 frames 0.016 deg against the INS's 0.008).
    """
    q = step_noise(d_R, np.asarray(inp.times, dtype=np.float64), valid)
    if q is None:
        return np.full(3, sig.odo_r)
    q = np.clip(q, sig.odo_r, ODO_R_CAP)
    for name, v in zip(("roll", "pitch", "heading"), q, strict=True):
        health.metrics[f"fused_odometry_step_{name}_deg"] = float(np.degrees(v))
    return q


#: INS speed (m/s) below which a step between two frames is a standstill (the INS velocity
#: is good to 0.005-0.02 m/s): the zero-velocity update replaces the ICP step there.
ZUPT_SPEED_MPS = 0.05
#: Rotation sigma of a standstill step (rad): a train that stands does not turn.
ZUPT_SIGMA_R = 0.001 * DEG
#: Floor of the translation sigma of a standstill step (m); above it, what the INS speed
#: allows over the step.
ZUPT_SIGMA_T_MIN = 0.0005
#: A sequence that stands throughout (INS travelled distance): its steps' sigmas (m, rad),
#: small enough that 100 chained steps stay below a hundredth of a pixel at 50 m (the
#: odometry of a standing train does not drift either: it re-registers one map).
STANDSTILL_SIGMA_T = 2e-5
STANDSTILL_SIGMA_R = 1e-5 * DEG
#: Half-width (frames) of the median filter on the INS speed for the standstill test.
ZUPT_WINDOW = 5


def zero_velocity_steps(
    ins: InsFrames, times: F64, d_t: F64, d_R: F64, w_t: F64, w_r: F64, health: Health
) -> NDArray[np.bool_]:
    """Standing steps (both frames' INS speed below ZUPT_SPEED_MPS): the relative motion
    becomes the identity with the sigmas a standstill allows (in place). ICP between two
    scans of the same scene jitters by millimetres and thousandths of a degree, which a
    12 MP camera shows as pixels at 30 m; the INS's zero speed is the better measurement."""
    raw = np.linalg.norm(ins.v_world, axis=1)
    if len(raw) < 2:
        return np.zeros(max(len(raw) - 1, 0), dtype=bool)
    # the velocity's noise (a few cm/s per axis) averaged out over +-ZUPT_WINDOW frames
    speed = median_filter(raw, size=2 * ZUPT_WINDOW + 1, mode="nearest")
    step_speed = 0.5 * (speed[1:] + speed[:-1])
    still = (speed[1:] < ZUPT_SPEED_MPS) & (speed[:-1] < ZUPT_SPEED_MPS)
    if ins.standstill:  # the whole sequence stands (INS travelled distance)
        still[:] = True
    if not np.any(still):
        return still
    dt = np.diff(times)[still]
    if ins.standstill:  # the train stands throughout: one pose, up to numerical noise
        sigma_t = np.full(len(dt), STANDSTILL_SIGMA_T)
        sigma_r = STANDSTILL_SIGMA_R
    else:
        sigma_t = np.maximum(step_speed[still] * dt, ZUPT_SIGMA_T_MIN)
        sigma_r = ZUPT_SIGMA_R
    d_t[still] = 0.0
    d_R[still] = np.eye(3)
    w_t[still] = 1.0 / sigma_t[:, None]
    w_r[still] = 1.0 / sigma_r
    health.metrics["fused_zero_velocity_steps"] = float(np.sum(still))
    return still


def build_problem(inp: LocalizationInput, health: Health, sig: Sigmas) -> Problem:
    """Initial guess and measurements of the smoothing problem."""
    ins = ins_at_frames(inp, health)
    n = len(inp.frames)
    p_ins_all = remove_jumps(ins.T_world_base[:, :3, 3], ins.jump_frames, ins.jump_steps)
    R_ins_all = ins.T_world_base[:, :3, :3]
    rail = None
    R0, p0 = R_ins_all.copy(), p_ins_all.copy()
    if inp.ego is not None:
        try:
            T_r, _, _ = rail_frames(inp.ego, p_ins_all)
            rail = _linearise_rails(inp.ego, p_ins_all, R_ins_all, sig)
            R0, p0 = rail["R"].copy(), T_r[:, :3, 3]
        except Exception as exc:
            health.warn(f"fused: rail constraint unusable ({exc}); without rails")
            rail = None
    else:
        health.warn("no rails found: fused runs without the rail constraint")
    T_first = None
    if n >= 2:
        D = odometry_deltas(inp)
        T_first = _map_first_steps(inp, D, health, sig)
    else:
        D = np.zeros((0, 4, 4))
    d_t, d_R = D[:, :3, 3].copy(), D[:, :3, :3].copy()
    heading_err = _heading_errors(inp, ins, health, sig)
    w_t, w_r, degenerate, odo_step_r = (
        _odometry_weights(inp, ins, d_t, d_R, health, sig, heading_err)
        if n >= 2
        else (np.zeros((0, 3)), np.zeros((0, 3)), False, None)
    )
    zupt = np.zeros(max(n - 1, 0), dtype=bool)
    if n >= 2:
        times = np.asarray(inp.times, dtype=np.float64)
        zupt = zero_velocity_steps(ins, times, d_t, d_R, w_t, w_r, health)
    heading = _heading_change_deg(R_ins_all)
    health.metrics["fused_heading_change_deg"] = heading
    lever_sigma = np.full(3, sig.lever)
    # A body-fixed forward lever arm is indistinguishable from the INS's along-track error
    # (in curves only barely: measured worse than keeping it): it stays at zero.
    lever_sigma[0] = 0.01
    bore_sigma = sig.boresight
    if rail is None:
        # Without rails only the direction of travel could tell the boresight, and the
        # INS's drift over a short sequence bends that by tenths of a degree: keep the
        # nominal misalignment.
        lever_sigma[:] = 0.01
        bore_sigma = 0.005 * DEG
    k = np.flatnonzero(ins.covered).astype(np.int64)
    if len(k) == 0:
        k = np.arange(n, dtype=np.int64)  # extrapolated INS is all there is
    knot_i, knot_a, n_knots = _bias_knots(
        np.asarray(inp.times, dtype=np.float64), k, sig.bias_knot_s
    )
    bias_sigma = np.array([sig.att_bias] * 3 + [sig.pos_bias] * 3)
    ground = _ground_constraints(inp, health, sig) if n >= 2 else None
    gyro = _gyro_steps(inp, d_R, w_r, ground, health, sig) if n >= 2 else None
    covered = np.asarray(ins.covered, dtype=bool)
    # the INS attitude's own white noise (third differences), for the heading's two uses
    own_white = white_noise(
        R_ins_all, np.asarray(inp.times, dtype=np.float64), covered[:-1] & covered[1:]
    )
    bias_step = _bias_step_sigmas(
        inp, ins, p_ins_all, degenerate, health, sig, ground, heading_err, own_white, odo_step_r
    )
    white = _ins_attitude_white(inp, ins, ground, health, sig, own_white)
    if rail is None:
        # Nothing else fixes the absolute attitude: the INS's is taken as is.
        bias_sigma[:3] = 0.005 * DEG
    odo_pairs = _odometry_pairs(inp, w_t, w_r, zupt, degenerate, health, sig, T_first, heading_err)
    accel = _accel_steps(inp, gyro, health, sig)
    yaw = 0.0 if odo_pairs is None else odo_pairs["yaw_offset"]
    pitch = 0.0 if ground is None else ground["pitch_offset"]
    if (yaw or pitch) and n >= 2:
        # KISS-ICP's steps (and pairs) are in the same turned and pitched cloud
        D_base = tilt_lidar_poses(turn_lidar_poses(D, yaw), pitch)
        d_t, d_R = D_base[:, :3, 3].copy(), D_base[:, :3, :3].copy()
    if pitch and odo_pairs is not None:
        odo_pairs["T_k_j"] = tilt_lidar_poses(odo_pairs["T_k_j"], pitch)
    return Problem(
        R0=R0,
        p0=p0,
        d_t=d_t,
        d_R=d_R,
        w_odo_t=w_t,
        w_odo_r=w_r,
        ins_k=k,
        p_ins=p_ins_all[k],
        R_ins=R_ins_all[k],
        w_ins=_rotvec_rates(R_ins_all, inp.times)[k],
        rail=rail,
        sig=sig,
        n=n,
        lever_sigma=lever_sigma,
        bore_sigma=bore_sigma,
        knot_i=knot_i,
        knot_a=knot_a,
        n_knots=n_knots,
        bias_sigma=bias_sigma,
        bias_step_sigma=bias_step,
        ground=ground,
        vel=_velocity_steps(inp, ins, health, sig) if n >= 2 else None,
        odo_pairs=odo_pairs,
        gyro=gyro,
        nh=_rail_motion(
            inp,
            n,
            sig,
            _bogie_sigma(health, degenerate, sig, math.radians(heading), n - 1),
        ),
        accel=accel,
        n_acc_knots=0 if accel is None else accel["n_knots"],
        acc_knot_i=np.zeros(0, dtype=np.int64) if accel is None else accel["knot_i"],
        acc_knot_a=np.zeros(0) if accel is None else accel["knot_a"],
        zupt=zupt,
        diff2=difference_weights(np.asarray(inp.times, dtype=np.float64), 2),
        diff3=difference_weights(np.asarray(inp.times, dtype=np.float64), 3),
        ins_r_share=_ins_attitude_factors(k, sig, bias_step, white),
        ins_white=white,
        R_bias=_track_axes(R_ins_all),
    )


def _gyro_steps(
    inp: LocalizationInput,
    d_R: F64,
    w_r: F64,
    ground: dict | None,
    health: Health,
    sig: Sigmas,
) -> dict | None:
    """The gyro block (:mod:`.gyro`): D (n-1, 3, 3) and w (n-1, 3), None without gyro
    records or when switched off. The record clock's offset is set against the ground
    pairs' roll and pitch (KISS-ICP's rotation steps ``d_R`` with their weights ``w_r``
    (n-1, 3) without ground); a step across a missing record is down-weighted."""
    if not (sig.gyro and inp.options.get("fused_gyro", True)):
        return None
    if ground is not None:
        w_g = np.zeros((len(ground["k"]), 3))
        w_g[:, :2] = ground["w"][:, 1:]
        ref = (ground["k"], ground["j"], ground["T_k_j"][:, :3, :3], w_g)
    else:
        k = np.arange(len(d_R), dtype=np.int64)
        ref = (k, k + 1, d_R, w_r)
    try:
        steps = gyro_steps(inp, ref, health)
    except ValueError as exc:
        health.warn(f"fused: gyro records unusable ({exc})")
        return None
    if steps is None or not np.any(steps.ok):
        return None
    sigma = np.hypot((sig.gyro_r * (1.0 + GAP_SIGMA_FACTOR * steps.gap))[:, None], steps.sd_interp)
    return {
        "D": steps.D,
        "w": np.where(steps.ok[:, None], 1.0 / sigma, 0.0),
        "dt": np.diff(np.asarray(inp.times, dtype=np.float64)),
        "steps": steps,
    }


def _accel_steps(
    inp: LocalizationInput, gyro: dict | None, health: Health, sig: Sigmas
) -> dict | None:
    """The accelerometer block (:mod:`.accelerometer`) on the gyros' chain and clock
    offset: meas and w (n-2, 3), h2 (a constant acceleration's share of a row) and the
    bias knots per row; None without gyro steps, records, or when switched off."""
    n = len(inp.frames)
    if gyro is None or n < 3 or not (sig.accel and inp.options.get("fused_accel", True)):
        return None
    steps = gyro["steps"]
    times = np.asarray(inp.times, dtype=np.float64)
    got = accel_block(
        inp,
        steps.chain,
        steps.offset_s,
        steps.imu_rate_hz,
        difference_weights(times, 2),
        sig.accel_diff,
        health,
    )
    if got is None:
        return None
    # a constant acceleration b adds b h^2 to each row (difference_weights' scale)
    dt = np.diff(times)
    h = float(np.median(dt)) if len(dt) and np.median(dt) > 0 else 1.0
    knot_i, knot_a, n_acc = _bias_knots(times, np.arange(1, n - 1), sig.accel_bias_knot_s)
    return {**got, "h2": h * h, "knot_i": knot_i, "knot_a": knot_a, "n_knots": n_acc}


def _acc_bias_knots_of(x: F64, pb: Problem) -> F64:
    """(n_acc_knots, 3) the accelerometers' bias knots (m/s^2, base axes)."""
    i0 = _acc_bias_col(pb.n, pb.n_knots)
    return x[i0 : i0 + 3 * pb.n_acc_knots].reshape(pb.n_acc_knots, 3)


def _accel_residuals(x: F64, pb: Problem, R: F64, p: F64) -> F64:
    """(n-2, 3) normalised residuals of the accelerometer block: the positions' second
    differences (base axes of each stencil's middle frame) against the accelerometers'
    less their bias at the middle frame (the accelerometers measure the base's
    acceleration plus the bias)."""
    assert pb.accel is not None
    c = pb.diff2
    a_world = c[:, :1] * p[:-2] + c[:, 1:2] * p[1:-1] + c[:, 2:] * p[2:]
    a_base = np.einsum("nji,nj->ni", R[1:-1], a_world)
    knots = _acc_bias_knots_of(x, pb)
    i, w = pb.acc_knot_i, pb.acc_knot_a[:, None]
    b = (1.0 - w) * knots[i] + w * knots[np.minimum(i + 1, pb.n_acc_knots - 1)]
    meas = pb.accel["meas"] - b * pb.accel["h2"]
    return (a_base - meas) * pb.accel["w"] / pb.s("accel")


#: Shortest run (m, the INS's travelled distance) on which the base's distance ahead of
#: its bogies is estimated (:attr:`Sigmas.bogie_offset`); shorter runs keep it at 0.
BOGIE_MIN_TRAVEL_M = 20.0
#: Least information (m^-2) the run's turn gives on the bogie offset for it to be
#: estimated: the offset moves the base sideways by itself times each step's turn, so
#: the lateral rail-motion rows measure it with information sum (turn_k / sigma_lat)^2,
#: taken as the run's heading change spread evenly over its steps. 1 m^-2: the turn alone
#: fixes the offset to 1 m. Where it does not (a straight), a free offset only gives the
#: heading a way to take up the lateral steps' errors (station-f35-d0.3-hard-s10-bogies-
#: blind, 0.06 deg of turn over 20 m: heading over 30 frames 0.050 deg free, 0.022 pinned,
#: the INS 0.040); in a curve (tight_curve, 10 deg over 60 frames: 500 m^-2) it is free.
BOGIE_MIN_INFORMATION = 1.0
#: The bogie offset's prior sigma (m) where it is not estimated.
BOGIE_PINNED_M = 1e-6


def bogie_information(heading_change_rad: float, n_steps: int, sigma_lat_m: float) -> float:
    """Information (m^-2) on the base's distance ahead of its bogies from a run that turns
    by ``heading_change_rad`` evenly over ``n_steps`` steps, lateral rows of
    ``sigma_lat_m``: ``n (dpsi / n)^2 / sigma^2``."""
    if n_steps < 1 or sigma_lat_m <= 0.0:
        return 0.0
    return float(heading_change_rad) ** 2 / n_steps / sigma_lat_m**2


def _bogie_sigma(
    health: Health, degenerate: bool, sig: Sigmas, heading_change_rad: float, n_steps: int
) -> float:
    """The prior sigma (m) of the base's distance ahead of its bogies on this run: free
    on a run long enough (:data:`BOGIE_MIN_TRAVEL_M`), not degenerate along the track, and
    turning enough to measure it (:data:`BOGIE_MIN_INFORMATION`); pinned at 0 otherwise."""
    travelled = float(health.metrics.get("ins_travelled_m", 0.0))
    info = bogie_information(heading_change_rad, n_steps, sig.rail_motion_lat)
    health.metrics["fused_bogie_information_m2"] = info
    free = not degenerate and travelled >= BOGIE_MIN_TRAVEL_M and info >= BOGIE_MIN_INFORMATION
    return sig.bogie_offset if free else BOGIE_PINNED_M


def _rail_motion(
    inp: LocalizationInput, n: int, sig: Sigmas, bogie_sigma: float = BOGIE_PINNED_M
) -> dict | None:
    """The rail-motion block: a rail vehicle's base point moves along the body's axis
    except for the chord of a turn, d times the turn for a base at distance d ahead of the
    midpoint of its two bogies (in a curve of radius r the body turns about the curve's
    centre; a point d ahead of the bogies' midpoint moves at d / r to the body's axis; d
    a state with the prior ``Sigmas.bogie_offset``) and the change of the body's sway
    on its suspension (per-frame offset and rate states under a damped oscillator's
    prior, :mod:`.body_sway`).

    Returns w (n-1, 2) 1/sigma of each step's lateral and vertical rows and sway, the
    :class:`~.body_sway.SwayPrior` of the lateral and the vertical offsets and
    bogie_sigma, the offset's prior sigma (m)."""
    if n < 2 or not (sig.rail_motion and inp.options.get("fused_rail_motion", True)):
        return None
    w_vert = 1.0 / sig.rail_motion_vert if sig.rail_motion_vert > 0 else 0.0
    w = np.column_stack([np.full(n - 1, 1.0 / sig.rail_motion_lat), np.full(n - 1, w_vert)])
    dt = np.maximum(np.diff(inp.times), 1e-3)
    sway = [oscillator_prior(dt, sig.sway[c], sig.sway_hz[c], sig.sway_damping) for c in range(2)]
    return {"w": w, "sway": sway, "bogie_sigma": float(bogie_sigma)}


def _rail_motion_residuals(pb: Problem, R: F64, p: F64, x: F64) -> F64:
    """((n-1) 2,) normalised residuals of the rail motion: frame k + 1's lateral position
    in frame k against the turn between them times (half the step + d) and the change of
    the sway, its height against the pitch between them times (half the step + d) (a
    pitch about +y, the left axis, lowers the nose) and the change of the bounce."""
    assert pb.nh is not None
    o, d = _sway_of(x, pb)
    B = np.einsum("nji,nj->ni", R[:-1], p[1:] - p[:-1])
    rot = _log_rotation(np.swapaxes(R[:-1], 1, 2) @ R[1:])
    do = np.diff(o, axis=0)
    lat = B[:, 1] - rot[:, 2] * (0.5 * B[:, 0] + d) - do[:, 0]
    vert = B[:, 2] + rot[:, 1] * (0.5 * B[:, 0] + d) - do[:, 1]
    return (np.column_stack([lat, vert]) * pb.nh["w"] / pb.s("nh")).ravel()


def _track_axes(R_world_base: F64) -> F64:
    """(3, 3) world axes of the sequence's mean heading (x forward, y left, z up) for
    (n, 3, 3) base attitudes."""
    x = R_world_base[:, :, 0]
    yaw = math.atan2(float(np.sum(x[:, 1])), float(np.sum(x[:, 0])))
    return Rotation.from_rotvec([0.0, 0.0, yaw]).as_matrix()


def _ins_attitude_factors(
    k: NDArray[np.int64], sig: Sigmas, bias_step: F64 | None, white: F64 | None = None
) -> F64:
    """(m, 3) factors on ``sig.ins_r`` per INS record and axis (roll, pitch, heading).

    The record's white noise (``white`` (3,) rad as measured by :func:`_ins_attitude_white`,
    else ``ins_r``) and, with ``ins_r_share``, what the INS's wander
    adds between the bias knots: a random walk of
    ``q`` per knot strays from its linear interpolation by q / sqrt(6) RMS (a Brownian
    bridge), which the piecewise-linear bias cannot follow; ``bias_step`` (6,) holds q
    about the world axes (horizontal, horizontal, vertical ~ roll, pitch, heading).
    """
    white = np.full(3, sig.ins_r) if white is None else np.asarray(white, dtype=np.float64)
    sigma = white
    if sig.ins_r_share and bias_step is not None:
        sigma = np.sqrt(white**2 + bias_step[:3] ** 2 / 6.0)
    return np.tile(sigma / sig.ins_r, (len(k), 1))


#: Fewest ground pairs of the longest lag for :func:`_ins_level_wander`.
MIN_NOISE_PAIRS = 5
#: Floor of a measured INS attitude white noise (rad): what a survey-grade INS's attitude
#: output reaches (its quantisation and filter noise), so that sampling luck on a short
#: sequence cannot make one source absolute.
INS_WHITE_FLOOR = 0.002 * DEG


def _ins_attitude_white(
    inp: LocalizationInput,
    ins: InsFrames,
    ground: dict | None,
    health: Health,
    sig: Sigmas,
    own: F64 | None = None,
) -> F64 | None:
    """(3,) the INS attitude's white noise per record (rad) about roll, pitch and heading,
    measured over one frame step, within [INS_WHITE_FLOOR, ``sig.ins_r``]; None when it
    cannot be measured (the fixed ``sig.ins_r`` then holds).

    Over one frame the INS's wander is negligible, so its relative rotation's error is
    its white noise twice. Roll and pitch come from the three-cornered hat of the INS, the
    odometry and the lag-1 ground pairs (each source's own error); the heading, with no
    third source, from the INS against the odometry (which counts the odometry's own step
    error as the INS's: an upper bound) or from the INS's own third differences
    (:func:`~.step_noise.white_noise`), whichever is smaller. A fixed 0.03 deg made a good INS
    (0.003 deg noise) count for a hundredth of its worth, and the fused rotation over 30
    frames followed the odometry's drift (0.034 deg against the INS's own 0.007).
    """
    try:
        T_odo = odometry_track(inp)[0].T
    except Exception:  # the wander measurement has warned already
        return None
    covered = np.asarray(ins.covered, dtype=bool)
    i = np.flatnonzero(covered[:-1] & covered[1:])
    if len(i) < MIN_NOISE_PAIRS:
        return None
    R_ins, R_odo = ins.T_world_base[:, :3, :3], T_odo[:, :3, :3]
    rel_ins = np.swapaxes(R_ins[i], 1, 2) @ R_ins[i + 1]
    rel_odo = np.swapaxes(R_odo[i], 1, 2) @ R_odo[i + 1]
    var = robust_rms(relative_difference(rel_ins, rel_odo)) ** 2
    if ground is not None:
        sel = (ground["j"] - ground["k"] == 1) & covered[ground["k"]] & covered[ground["j"]]
        kk, jj = ground["k"][sel], ground["j"][sel]
        v = hat_variances(
            {
                "ins": np.swapaxes(R_ins[kk], 1, 2) @ R_ins[jj],
                "odometry": np.swapaxes(R_odo[kk], 1, 2) @ R_odo[jj],
                "ground": ground["T_k_j"][sel][:, :3, :3],
            }
        )
        if v is not None:
            var[:2] = v["ins"]
    if own is not None:  # the heading against the odometry counts the odometry's step error
        var[2] = min(var[2], 2.0 * own[2] ** 2)
    white = np.clip(np.sqrt(var / 2.0), INS_WHITE_FLOOR, sig.ins_r)
    for name, w in zip(("roll", "pitch", "heading"), white, strict=True):
        health.metrics[f"fused_ins_white_{name}_deg"] = float(np.degrees(w))
    return white


def _velocity_steps(
    inp: LocalizationInput, ins: InsFrames, health: Health, sig: Sigmas
) -> dict | None:
    """The INS velocity as a measurement of each step's displacement, along the track and
    sideways.

    The velocity is what an INS measures best (cm/s, Doppler-aided, immune to GNSS jumps):
    over a 0.1 s step it fixes the along-track displacement to millimetres, where lidar
    odometry degenerates on long straights and lags on slow trains. The world
    displacement it gives is compared on the solution's own forward and lateral axes, so
    the INS's attitude does not enter (its heading is off by tenths of a degree to a
    degree; taken along the INS's forward axis, such an error against a body crabbing in
    a curve shortened the steps by 0.05 %); its error is the velocity's own, millimetres a
    second. Over a short run the
    body's sway has a mean lateral velocity that only the sway states bound (a
    6 mm sway at 0.7 Hz moves at up to 26 mm/s); the INS velocity sees it. Sigma: the
    INSSTDEV velocity stdev the INS reports (median per axis, within ``ins_v_bounds``),
    else the bounds' upper end; the variance factors then correct it from the residuals.
    Steps whose frames lack an INS record of their own are left out.
    Returns k (S,), dp (S, 3) the world displacement and w (S,) 1 / sigma.
    """
    if not sig.use_ins_velocity:
        return None
    v = ins.v_world
    if len(v) < 2 or not np.any(np.linalg.norm(v, axis=1) > 0):
        return None
    times = np.asarray(inp.times, dtype=np.float64)
    dt = np.diff(times)
    k = np.flatnonzero(ins.covered[:-1] & ins.covered[1:] & (dt > 0)).astype(np.int64)
    if len(k) == 0:
        return None
    lo, hi = sig.ins_v_bounds
    sigma_v = hi
    try:
        sd = inp.sequence.ins_stdev()
        cols = [sd.east_velocity_stdev, sd.north_velocity_stdev, sd.up_velocity_stdev]
        vals = np.concatenate([np.asarray(c, dtype=np.float64) for c in cols])
        vals = vals[np.isfinite(vals)]
        if len(vals):
            sigma_v = float(np.clip(np.median(vals), lo, hi))
    except (OSError, ValueError, AttributeError) as exc:
        log.debug("no INS velocity stdev (%s): sigma %.3f m/s", exc, sigma_v)
    health.metrics["fused_ins_velocity_sigma_mps"] = sigma_v
    dp = 0.5 * (v[k] + v[k + 1]) * dt[k][:, None]
    return {"k": k, "dp": dp, "w": 1.0 / (sigma_v * dt[k])}


def full_weight_steps(
    w_t: F64, w_r: F64, zupt: NDArray[np.bool_], odo_t: float, along: bool
) -> NDArray[np.bool_]:
    """(n-1,) the odometry steps at full weight: moving (not a zero-velocity step), lateral
    (and vertical, weighted with it) at ``1 / odo_t`` (a run degenerate along the track,
    ``along`` False: at the run's lateral weight, ``1 / (DEGENERATE_DIVISOR odo_t)``),
    along the track too if ``along``, and a rotation weight the largest of the moving
    steps' (no skipped, slipping or degenerate step). w_t, w_r : (n-1, 3) the steps'
    weights (:func:`_odometry_weights`)."""
    moving = ~zupt if len(zupt) else np.ones(len(w_t), dtype=bool)
    w_r_full = np.max(w_r[moving], axis=0) if np.any(moving) else np.zeros(3)
    w_lat = 1.0 / odo_t if along else 1.0 / (DEGENERATE_DIVISOR * odo_t)
    full = moving & (w_t[:, 1] >= 0.99 * w_lat) & np.all(w_r >= 0.99 * w_r_full, axis=1)
    if along:
        full &= w_t[:, 0] >= 0.99 / odo_t
    return full


def _odometry_pairs(
    inp: LocalizationInput,
    w_t: F64,
    w_r: F64,
    zupt: NDArray[np.bool_],
    degenerate: bool,
    health: Health,
    sig: Sigmas,
    T_odom: F64 | None = None,
    heading: HeadingErrors | None = None,
) -> dict | None:
    """KISS-ICP's relative positions and headings over ``sig.odo_pair_lags`` frames as
    measurements (its poses, or ``T_odom`` (n, 4, 4): the same with the first frames
    refined). The heading's sigma is at least what the heading hat measured of the
    odometry's (``heading``, over its lag, scaled to each lag as a random walk): an
    odometry that misses a slow curve (0.57 deg over 10 frames) must not turn a good INS.

    A pair (k, k + lag) is kept when every step between its frames is a full-weight ICP
    step (no skipped, slipping or degenerate step, no standstill: those steps' own
    weights already say what the odometry is worth there); a run degenerate along the
    track keeps only the lateral component. The lag-L pairs of consecutive k share L - 1
    steps: their sigmas are multiplied by sqrt(L) so that together they count about as
    one pair a lag apart, by sqrt(count) where fewer than L pairs are kept (a sequence
    shorter than two lags: its few pairs overlap in most steps and count as one). A lag
    longer than the run is replaced by the run's whole length (``sig.odo_pair_whole_run``:
    one pair) where the odometry is not degenerate along the track.
    Returns k, j (Q,), T_k_j (Q, 4, 4) and w (Q, 3): 1/sigma of frame j's position in
    frame k along the track and laterally, and of its heading (``sig.odo_pair_r_a``)."""
    n = len(inp.frames)
    lags = sorted({int(L) for L in sig.odo_pair_lags if 0 < int(L) < n})
    if (
        sig.odo_pair_whole_run
        and not degenerate
        and n - 1 >= MIN_WHOLE_RUN_LAG
        and max(sig.odo_pair_lags, default=0) >= n
    ):
        lags = sorted(set(lags) | {n - 1})
    if not lags or len(w_t) == 0:
        return None
    try:
        T = odometry_run(inp).T_odom_base if T_odom is None else T_odom
    except Exception as exc:
        health.warn(f"fused: no odometry pairs ({exc})")
        return None
    full = full_weight_steps(w_t, w_r, zupt, sig.odo_t, along=not degenerate)
    bad = np.concatenate([[0], np.cumsum(~full)])  # bad steps before frame i
    ks, js, wt = [], [], []
    for L in lags:
        k = np.arange(n - L)
        k = k[bad[k + L] - bad[k] == 0]
        if not len(k):
            continue
        share = np.sqrt(min(len(k), L))
        sigma = (np.asarray(sig.odo_pair_t_a) + L * np.asarray(sig.odo_pair_t_b)) * share
        sigma_h = sig.odo_pair_r_a + L * sig.odo_pair_r_b
        if heading is not None:
            sigma_h = max(sigma_h, math.sqrt(heading.odometry * L / heading.lag))
        sigma_h *= share
        w = np.tile(np.r_[1.0 / sigma, 1.0 / sigma_h if sig.odo_pair_r_a > 0 else 0.0], (len(k), 1))
        if degenerate:
            w[:, 0] = 0.0
        ks.append(k)
        js.append(k + L)
        wt.append(w)
    if not ks:
        return None
    k = np.concatenate(ks).astype(np.int64)
    j = np.concatenate(js).astype(np.int64)
    T_k_j = np.linalg.inv(T[k]) @ T[j]
    w = np.concatenate(wt)
    health.metrics["fused_odometry_pairs"] = float(len(k))
    delta, fine = 0.0, np.zeros(len(k), dtype=bool)
    if sig.scan_pairs and inp.options.get("fused_scan_pairs", True) and not degenerate:
        delta, fine = _fine_pairs(inp, k, j, T_k_j, w, health, sig)
    if delta:
        T_k_j = turn_lidar_poses(T_k_j, delta)
    return {"k": k, "j": j, "T_k_j": T_k_j, "w": w, "yaw_offset": delta, "fine": fine}


#: Fewest frames after the first ``map_first_steps`` for their map to be worth registering
#: onto: on a 6-frame sparse sequence (a map of 3 scans) the refined first frames bent the
#: poses so far that the prepared ego track ended 9.5 m ahead.
MIN_MAP_FRAMES = 6


def _map_first_steps(inp: LocalizationInput, D: F64, health: Health, sig: Sigmas) -> F64 | None:
    """KISS-ICP's first ``sig.map_first_steps`` steps re-registered against a mature local
    map: frames ``K - 1`` down to 0 each registered (:func:`.scan_pairs.register_to_map`,
    point-to-plane) onto the scans of frames ``K`` to ``K + sig.map_first_frames - 1``
    merged with KISS-ICP's poses, and ``D`` (n-1, 4, 4) rewritten from the refined poses,
    in place; returns KISS-ICP's poses (n, 4, 4) with the refined first ones (for the
    odometry pairs), None where nothing was done. Frames whose registration fails a gate
    keep KISS-ICP's pose.

    KISS-ICP registers its first frames against a local map of one to three scans: on the
    sparse matrix cells those steps were 50-80 mdeg of heading off, and every later pose
    keeps that turn against the first frame, where an object is placed
    (tight_curve-f100-d0.3-osdar23-s0: the anchor 34 px off on rgb_highres_center).
    A mature map fixes what a scan-to-scan registration of sparse scans could not (its
    own heading was 30-45 mdeg off at lag 1)."""
    K = int(inp.options.get("fused_map_first_steps", sig.map_first_steps))
    n = len(D) + 1
    if (
        K <= 0
        or n < K + MIN_MAP_FRAMES
        or not sig.scan_pairs
        or not inp.options.get("fused_scan_pairs", True)
    ):
        return None
    T = odometry_run(inp).T_odom_base.copy()
    map_frames = np.arange(K, min(n, K + sig.map_first_frames), dtype=np.int64)
    done = 0
    for k in range(K - 1, -1, -1):
        got = register_to_map(inp, k, map_frames, T)
        if got is not None:
            T[k] = got
            done += 1
    D[:K] = np.linalg.inv(T[:K]) @ T[1 : K + 1]
    health.metrics["fused_first_frames_to_map"] = float(done)
    return T


#: Shortest lag of the odometry pair over a whole run shorter than a lag.
MIN_WHOLE_RUN_LAG = 4

#: Fewest closures (:func:`.scan_pairs.closure_factor`) to scale the scan pairs by.
MIN_CLOSURES = 3


#: Residual components of an odometry pair (:func:`_odometry_pair_residuals`).
ODO_PAIR_COMPONENTS = 4


def _fine_pairs(
    inp: LocalizationInput,
    k: NDArray[np.int64],
    j: NDArray[np.int64],
    T_k_j: F64,
    w: F64,
    health: Health,
    sig: Sigmas,
) -> tuple[float, NDArray[np.bool_]]:
    """The odometry pairs' lateral component from the fine scan-to-scan registration
    (:mod:`.scan_pairs`) where it is sharper than KISS-ICP's: ``T_k_j`` (Q, 4, 4) and
    ``w`` (Q, 2) updated in place. Independent registrations: no sqrt(lag) sharing.
    Returns the merged cloud's yaw against the base (:mod:`.lidar_yaw`, rad) where the
    pairs show one beyond twice its standard error (``sig.lidar_yaw``), else 0; and (Q,)
    which pairs took the fine lateral component."""
    fine = register_pairs(inp, k, j, T_k_j)
    sigma = np.maximum(fine.sd_t[:, 1], sig.scan_pair_lat_floor)
    lags = sorted({int(L) for L in np.unique(j - k)})
    if len(lags) >= 2 and inp.options.get("fused_scan_pair_closure", True):
        f, m = closure_factor(fine, lags[0], lags[-1])
        health.metrics["fused_scan_pair_closure"] = f
        health.metrics["fused_scan_pair_closures"] = float(m)
        if m >= MIN_CLOSURES:
            sigma = sigma * max(f, 1.0)
    use = fine.ok & (1.0 / sigma > w[:, 1])
    T_k_j[use, 1, 3] = fine.T_k_j[use, 1, 3]
    w[use, 1] = 1.0 / sigma[use]
    health.metrics["fused_scan_pairs"] = float(np.sum(use))
    if not (sig.lidar_yaw and inp.options.get("fused_lidar_yaw", True)):
        return 0.0, use
    est = lidar_yaw_offset(fine.T_k_j, fine.ok, j - k)
    if est is None:
        return 0.0, use
    health.metrics["fused_lidar_yaw_mrad"] = 1000.0 * est.rad
    health.metrics["fused_lidar_yaw_se_mrad"] = 1000.0 * est.se_rad
    return (est.rad if est.significant else 0.0), use


def _odometry_pair_residuals(pb: Problem, R: F64, p: F64) -> F64:
    """(Q, 4) normalised residuals of the odometry pairs: frame j's position in frame k
    against the odometry's, along the track, laterally from KISS-ICP and laterally from the
    fine registration (frame k's axes; each pair's other lateral column is 0), and frame
    j's heading in frame k against KISS-ICP's. The two lateral sources are separate
    components so that each gets its own variance factor: a sparse scan's registration can
    sit 2-10 cm from the truth with a formal sigma of 5 mm
    (station-f35-d0.3-hard-s0-bogies-blind), and its residuals then say so."""
    g = pb.odo_pairs
    assert g is not None
    Rk = R[g["k"]]
    B_t = np.einsum("nji,nj->ni", Rk, p[g["j"]] - p[g["k"]])
    E_t = (B_t[:, :2] - g["T_k_j"][:, :2, 3]) * g["w"][:, :2]
    fine = g["fine"]
    out = np.zeros((len(E_t), ODO_PAIR_COMPONENTS))
    out[:, 0] = E_t[:, 0]
    out[~fine, 1] = E_t[~fine, 1]
    out[fine, 2] = E_t[fine, 1]
    if np.any(g["w"][:, 2]):
        M_t = np.swapaxes(g["T_k_j"][:, :3, :3], 1, 2)
        E_r = _log_rotation(M_t @ np.swapaxes(Rk, 1, 2) @ R[g["j"]])
        out[:, 3] = E_r[:, 2] * g["w"][:, 2]
    return out / pb.s("odo_pair")


def _ground_constraints(inp: LocalizationInput, health: Health, sig: Sigmas) -> dict | None:
    """Ground pairs over the odometry's relative poses as residual data (or None)."""
    try:
        run = odometry_run(inp)
    except Exception as exc:
        health.warn(f"fused: no ground pairs (odometry unavailable: {exc})")
        return None
    skipped = set(run.skipped)
    lags = tuple(sig.ground_lags)
    # The odometry computed the default lags' pairs as it went (odometry.run_kiss_icp).
    found = run.ground_pairs if lags == GROUND_LAGS and run.ground_pairs is not None else None
    if found is None:
        found = ground_pairs(run.grounds, run.T_odom_base, lags)
    pairs = [pr for pr in found if pr.k not in skipped and pr.j not in skipped]
    health.metrics["fused_ground_pairs"] = float(len(pairs))
    if not pairs:
        health.warn("fused: no ground seen in common by frame pairs; height and pitch drift")
        return None
    lag = np.array([pr.j - pr.k for pr in pairs], dtype=np.float64)
    sigma = np.asarray(sig.ground_sigma_a)[None, :] + lag[:, None] * np.asarray(sig.ground_sigma_b)
    health.metrics["fused_ground_rms_m"] = float(np.median([pr.rms_m for pr in pairs]))
    k = np.array([pr.k for pr in pairs], dtype=np.int64)
    j = np.array([pr.j for pr in pairs], dtype=np.int64)
    T_k_j = np.array([pr.T_k_j for pr in pairs])
    pitch = 0.0
    if sig.lidar_pitch and inp.options.get("fused_lidar_pitch", True):
        est = lidar_pitch_offset(T_k_j, np.ones(len(k), dtype=bool), j - k)
        if est is not None:
            health.metrics["fused_lidar_pitch_mrad"] = 1000.0 * est.rad
            health.metrics["fused_lidar_pitch_se_mrad"] = 1000.0 * est.se_rad
            if est.significant:
                pitch = est.rad
                T_k_j = tilt_lidar_poses(T_k_j, pitch)
    long = (lag > lag.min()).astype(np.float64)
    return {
        "k": k,
        "j": j,
        "T_k_j": T_k_j,
        "w": 1.0 / sigma,
        "pitch_offset": pitch,
        "long": long,
    }


def _bias_step_sigmas(
    inp: LocalizationInput,
    ins: InsFrames,
    p_ins: F64,
    degenerate: bool,
    health: Health,
    sig: Sigmas,
    ground: dict | None = None,
    heading: HeadingErrors | None = None,
    own_white: F64 | None = None,
    odo_step_r: F64 | None = None,
) -> F64:
    """(6,) sigmas of the INS bias' change between knots: attitude about the track's axes
       (roll, pitch, heading: :func:`_track_axes`, rad), position along world x, y, z (m),
       from the INS's wander against the odometry (roll and pitch against the ground pairs
       where there are some: :func:`_ins_level_wander`).
    Where the odometry is degenerate along the track it cannot judge
       the INS positions, whose wander is then measured against the INS velocity
       (:func:`_position_wander_against_velocity`; the floor without one).
    ``odo_step_r`` (3,): the odometry's step noise (rad, roll, pitch, heading), which a
       wander measured over a shortened lag must clearly exceed to count.
    """
    a_floor, a_default, a_cap = sig.att_bias_step
    p_floor, p_default, p_cap = sig.pos_bias_step
    out = np.array([a_default] * 3 + [p_default] * 3)
    try:
        T_odo = odometry_track(inp)[0].T
    except Exception as exc:
        health.warn(f"fused: INS wander not measured (no odometry: {exc}); default sigmas")
        return out
    T_ins = ins.T_world_base.copy()
    T_ins[:, :3, 3] = p_ins
    times = np.asarray(inp.times, dtype=np.float64)
    w = ins_wander(T_ins, T_odo, times, ins.covered, sig.bias_knot_s)
    if w is None:
        return out
    rot = w.rotation_rad.copy()
    level = _ins_level_wander(
        ins.T_world_base[:, :3, :3], T_odo[:, :3, :3], ground, times, sig.bias_knot_s
    )
    floor = np.full(3, a_floor)
    if level is not None:  # the ground's roll and pitch drift far less than the odometry's
        rot[:2] = level
        # The hat measures the INS's own wander, not a bound: it may go below the floor
        # that guards the odometry-only measurement (a good INS wanders by thousandths of
        # a degree a second; held to 0.01 deg its roll over 30 frames followed the
        # odometry's, 0.017 deg against its own 0.002).
        floor[:2] = INS_WHITE_FLOOR
        health.metrics["fused_ins_wander_source_level"] = 1.0
    if heading is not None:  # the course over ground is the heading's third source
        white_var = 2.0 * float(own_white[2]) ** 2 if own_white is not None else 0.0
        span = heading.lag * float(np.median(np.diff(times)))
        # within what it differs from the odometry by (both errors add up there)
        own_wander = math.sqrt(max(heading.ins - white_var, 0.0) * sig.bias_knot_s / span)
        rot[2] = min(rot[2], own_wander)
        floor[2] = INS_WHITE_FLOOR
        health.metrics["fused_ins_wander_source_heading"] = 1.0
    out[:3] = np.clip(rot, floor, a_cap)  # about the track's axes (Problem.R_bias)
    out[3:] = np.clip(w.position_m, p_floor, p_cap)
    if w.shortened:
        # Over a lag shorter than the knot spacing (a sequence too short for enough pairs
        # at the knots' lag) a large wander is plain (an osdar23-like INS turning 0.2 deg a
        # second against the odometry), a small one is not shown: its few overlapping
        # pairs mostly measure the odometry's noise. So it only loosens the default (with
        # the default 0.1 deg the fused heading of a 10-frame straight sparse run followed
        # the INS's turn, 16 px of anchor error against the odometry's 3; held to a
        # good INS's measured 0.01 deg a 10-frame station's went from 0.4 to 0.8 px).
        # (roll, pitch and heading measured by the ground pairs and the course keep theirs)
        # A difference is the INS's only where it is well above what the odometry's own
        # step noise adds up to over the lag (switch-f10-d0.3-hard-s0: 0.069 deg over 3
        # frames against steps of 0.037 deg, the hard INS's real wander 0.01 deg a second).
        from_odometry = np.array([level is None, level is None, heading is None])
        plain = np.ones(3, dtype=bool)
        if odo_step_r is not None:
            steps = w.measured_lag_s / max(float(np.median(np.diff(times))), 1e-9)
            at_lag = w.rotation_rad * (w.measured_lag_s / w.lag_s)
            plain = at_lag > SHORT_WANDER_SIGNIFICANCE * odo_step_r * math.sqrt(steps)
        loosened = np.where(plain, np.maximum(out[:3], a_default), a_default)
        out[:3] = np.where(from_odometry, loosened, out[:3])
        out[3:] = p_default
        health.metrics["fused_ins_wander_lag_s"] = w.measured_lag_s
    if degenerate:
        out[3:] = p_floor
        vel = (
            _position_wander_against_velocity(ins, p_ins, times, sig)
            if sig.use_ins_velocity and sig.ins_p_wander_from_velocity
            else None
        )
        if vel is not None:
            out[3:] = np.clip(vel, p_floor, p_cap)
            health.metrics["fused_ins_wander_against_velocity_m"] = float(np.max(vel))
    for name, v, used in zip(("roll", "pitch", "heading"), rot, out[:3], strict=True):
        health.metrics[f"fused_ins_wander_{name}_deg"] = float(np.degrees(v))
        health.metrics[f"fused_ins_bias_step_{name}_deg"] = float(np.degrees(used))
    for name, v in zip(("east", "north", "up"), w.position_m, strict=True):
        health.metrics[f"fused_ins_wander_{name}_m"] = float(v)
    return out


def _position_wander_against_velocity(
    ins: InsFrames, p_ins: F64, times: F64, sig: Sigmas
) -> F64 | None:
    """(3,) the INS positions' wander (m, east, north, up) over one knot spacing against
    the INS's own velocity integrated (None without velocities or enough pairs).

    Where the odometry is degenerate along the track it cannot judge the INS positions;
    the INS velocity can (it carries the along-track steps then, :func:`_velocity_steps`).
    A GNSS jump that the INS's filter pulls back over seconds is taken out as a step by
    :func:`remove_jumps`, and its decay is then a drift of the positions against the
    velocity (straight_sparse-f100-d0.3-hard-s11: two 0.75 m jumps decaying over 5 s
    left the positions 0.58 m short over 200 m, where the velocity's integral was within
    1 cm; held at the floor's 2 cm a knot the positions held fused 0.21 m short)."""
    v = ins.v_world
    if len(v) < 2 or not np.any(np.linalg.norm(v, axis=1) > 0):
        return None
    steps = 0.5 * (v[1:] + v[:-1]) * np.diff(times)[:, None]
    T_vel = ins.T_world_base.copy()
    T_vel[:, :3, 3] = p_ins[0] + np.vstack([np.zeros(3), np.cumsum(steps, axis=0)])
    T_ins = ins.T_world_base.copy()
    T_ins[:, :3, 3] = p_ins
    w = ins_wander(T_ins, T_vel, times, ins.covered, sig.bias_knot_s)
    return None if w is None else np.asarray(w.position_m, dtype=np.float64)


#: A wander measured over a shortened lag loosens the default only where the INS's
#: difference from the odometry is this many times the odometry's step noise over the lag.
SHORT_WANDER_SIGNIFICANCE = 2.0


def _ins_level_wander(
    R_ins: F64, R_odo: F64, ground: dict | None, times: F64, knot_s: float
) -> F64 | None:
    """(2,) the INS's roll and pitch wander (rad) over one knot spacing, None without
    enough ground pairs.

    Three independent measures of the relative roll and pitch over the ground pairs'
    longest lag - the INS, the ground pairs and the odometry - give each one's own error
    variance from the variances of their pairwise differences (:mod:`.hat`). Measured
    against the odometry
    alone, a good INS looked five times worse than it is (the odometry's drift counted as
    the INS's). Scaled to the knot spacing as a random walk.
    """
    if ground is None or len(times) < 2:
        return None
    lags = ground["j"] - ground["k"]
    lag = int(np.max(lags))
    sel = lags == lag
    if lag < 2 or int(np.sum(sel)) < MIN_NOISE_PAIRS:
        return None

    def ins_variance(sel: NDArray[np.bool_]) -> F64 | None:
        kk, jj = ground["k"][sel], ground["j"][sel]
        rel = {
            "ins": np.swapaxes(R_ins[kk], 1, 2) @ R_ins[jj],
            "odometry": np.swapaxes(R_odo[kk], 1, 2) @ R_odo[jj],
            "ground": ground["T_k_j"][sel][:, :3, :3],
        }
        v = hat_variances(rel)
        return None if v is None else v["ins"]

    v = ins_variance(sel)
    if v is None:
        return None
    # less the white noise, which the one-step pairs show (see ins_wander)
    v1 = ins_variance(lags == 1)
    if v1 is not None:
        v = np.maximum(v - v1, 0.0)
    kk, jj = ground["k"][sel], ground["j"][sel]
    span = float(np.median(times[jj] - times[kk]))
    return np.sqrt(v) * np.sqrt(knot_s / max(span, 1e-3))


def _heading_change_deg(R_world_base: F64) -> float:
    """Spread (deg) of the forward axis' heading over the sequence."""
    x = R_world_base[:, :, 0]
    yaw = np.unwrap(np.arctan2(x[:, 1], x[:, 0]))
    return float(np.degrees(np.ptp(yaw))) if len(yaw) else 0.0


def _frame_period(pb: Problem) -> int:
    """The smallest period P >= 3 such that no residual row touches two frames a multiple
    of P apart: rows link frames 1 and 2 apart (odometry, smoothness) and the ground pairs'
    lags."""
    gaps = {1, 2, 3} if pb.sig.jerk is not None or pb.accel is not None else {1, 2}
    if pb.ground is not None:
        gaps |= {int(d) for d in np.unique(pb.ground["j"] - pb.ground["k"])}
    if pb.odo_pairs is not None:
        gaps |= {int(d) for d in np.unique(pb.odo_pairs["j"] - pb.odo_pairs["k"])}
    period = 3
    while any(d % period == 0 for d in gaps):
        period += 1
    return period


def _column_groups(
    n: int,
    n_knots: int,
    period: int = 3,
    n_acc_knots: int = 0,
    extra: dict[str, int] | None = None,
) -> list[NDArray[np.int64]]:
    """Columns that share no residual row (finite differences in one evaluation each).

    A residual row touches frames that are never a multiple of ``period`` apart
    (:func:`_frame_period`), the misalignment and two consecutive bias knots, so frame
    columns with the same (frame mod period, component) go together, as do knot columns
    with the same (knot mod 3, component); the 7 misalignment columns each stand alone,
    the first three each with one of the gyro bias' (which only gyro rows touch). The
    accelerometer bias knots (only accelerometer rows touch them) join the INS bias
    knots' groups of the same phase. The sway offsets (only rail-motion rows and their
    priors touch them) of frames 2 apart go together, per component, beside the last four
    misalignment columns, their rates (only the priors of one axis each) the same way
    beside the first four; the bogie offset and the ground pairs' roll drift beside the
    first, their pitch drift beside the second, the cloud's pitch beside the third
    (``extra``: :func:`_extra_cols`).
    """
    groups = []
    for phase in range(period):
        for comp in range(6):
            frames = np.arange(phase, n, period)
            if len(frames):
                groups.append(6 * frames + comp)
    gb = _gyro_bias_col(n, n_knots)
    a0 = _acc_bias_col(n, n_knots)
    extra = extra or {}
    beside: list[list[int]] = [[gb], [gb + 1], [gb + 2], [], [], [], []]
    if "sway" in extra:
        s0 = extra["sway"]
        beside[0].append(extra["bogie"])
        v0 = extra["sway_rate"]
        for i, (phase, comp) in enumerate(((0, 0), (0, 1), (1, 0), (1, 1))):
            beside[3 + i] += list(s0 + 2 * np.arange(phase, n, 2) + comp)
            # the rates, which only the sway's prior rows touch (one axis each), beside the
            # columns no such row touches: the lever, the gyro bias, bogie, cloud pitch,
            # and the other axis' offsets
            beside[i] += list(v0 + 2 * np.arange(phase, n, 2) + comp)
    if "cloud_pitch" in extra:
        beside[2].append(extra["cloud_pitch"])
    if "ground_tilt" in extra:  # ground roll rows only (the cloud's pitch: height rows)
        beside[0].append(extra["ground_tilt"])
    if "ground_pitch" in extra:  # the longer ground pairs' pitch rows only
        beside[1].append(extra["ground_pitch"])
    groups.extend(np.array([6 * n + j, *beside[j]], dtype=np.int64) for j in range(7))
    for phase in range(3):
        for comp in range(6):
            knots = np.arange(phase, n_knots, 3)
            acc = a0 + 3 * np.arange(phase, n_acc_knots, 3) + comp if comp < 3 else []
            cols = np.concatenate([6 * n + 7 + 6 * knots + comp, acc]).astype(np.int64)
            if len(cols):
                groups.append(cols)
    return groups


#: Forward-difference step of the Jacobian (relative to max(1, |x|)). The stiffest rows
#: (standstill and INS-speed steps: weights up to 1e5 per metre) make rounding, not
#: truncation, the error: the solution's noise between runs was 5e-7 m along the track at
#: 1e-6, 2-5e-6 at 1e-7 and 3-6e-8 at 1e-5 (the residuals are nearly linear there).
FD_STEP = 1e-5


def _groups(pb: Problem) -> list[NDArray[np.int64]]:
    """:func:`_column_groups` of ``pb``."""
    return _column_groups(pb.n, pb.n_knots, _frame_period(pb), pb.n_acc_knots, _extra_cols(pb))


def jacobian(x: F64, r0: F64, pb: Problem, S: csc_matrix, groups: list) -> csc_matrix:
    """Sparse forward-difference Jacobian of :func:`residuals` at ``x``."""
    rows_all, cols_all, vals_all = [], [], []
    indptr, indices = S.indptr, S.indices
    R, p, *_ = _unpack(x, pb)
    for cols in groups:
        h = FD_STEP * np.maximum(1.0, np.abs(x[cols]))
        xh = x.copy()
        xh[cols] += h
        # columns of the misalignment and the INS bias leave the poses as they are
        same = (R, p, r0) if cols.min() >= 6 * pb.n else None
        dr = residuals(xh, pb, same) - r0
        for c, hc in zip(cols, h, strict=True):
            rows = indices[indptr[c] : indptr[c + 1]]
            rows_all.append(rows)
            cols_all.append(np.full(len(rows), c))
            vals_all.append(dr[rows] / hc)
    return csc_matrix(
        (np.concatenate(vals_all), (np.concatenate(rows_all), np.concatenate(cols_all))),
        shape=S.shape,
    )


#: Gauss-Newton stops once no parameter moves by more than this (m, rad, s: 10 um, 2e-4 deg
#: - 0.5 mm at 50 m); the Jacobian is kept from the previous iteration once the step is
#: below ``REUSE_JACOBIAN_STEP`` (the problem is nearly linear there: the reused Jacobian
#: slows convergence only by a few decimals, each new one costs ~43 residual evaluations).
STEP_TOL = 1e-5
REUSE_JACOBIAN_STEP = 1e-3


#: Up to this many parameters the normal equations are solved dense (Cholesky of a
#: 650 x 650 matrix, 100 frames: 3 ms against 30 ms for the sparse LU; 2000: 90 ms, 32 MB).
DENSE_MAX_PARAMS = 2000


#: Ridge added to the unit-diagonal scaled normal matrix (:func:`_normal_step`).
RELATIVE_RIDGE = 1e-10


def _normal_step(A: Any, g: F64) -> F64:
    """Solve ``(A + 1e-9 I) dx = g`` for the sparse normal matrix ``A`` (n, n).

    Solved with the columns scaled to a unit diagonal (Jacobi): the weights span ten
    orders of magnitude (a standstill's 0.5 mm step against a 2 m bias prior), and without
    the scaling the dense and sparse solvers' rounding differed by micrometres along the
    track, the least observed direction.
    """
    n = A.shape[0]
    if n <= DENSE_MAX_PARAMS:
        Ad = A.toarray()
        Ad[np.diag_indices(n)] += 1e-9
        d = 1.0 / np.sqrt(np.maximum(np.diag(Ad), 1e-300))
        Ad *= d[:, None]
        Ad *= d[None, :]
        Ad[np.diag_indices(n)] += RELATIVE_RIDGE
        try:
            return d * cho_solve(cho_factor(Ad, check_finite=False), d * g, check_finite=False)
        except LinAlgError:
            pass  # not positive definite (numerically): the LU below copes
    A = A.tocsc() + 1e-9 * identity(n, format="csc")
    d = 1.0 / np.sqrt(np.maximum(A.diagonal(), 1e-300))
    D = diags(d, format="csc")
    As = (D @ A @ D + RELATIVE_RIDGE * identity(n, format="csc")).tocsc()
    return d * spsolve(As, d * g)


def solve(pb: Problem, x0: F64 | None = None, max_iter: int = 8) -> F64:
    """Gauss-Newton with Huber weights (IRLS) on the sparse problem; the parameter vector.

    The problem is nearly linear (small rotation corrections), so a few iterations converge;
    a small Levenberg damping keeps the unobservable directions at their priors.
    """
    x = np.zeros(n_params(pb)) if x0 is None else x0.copy()
    S = _cached_sparsity(pb)
    groups = _groups(pb)
    c = pb.sig.huber
    J, step, fresh = None, np.inf, False
    for it in range(max_iter + 1):
        r = residuals(x, pb)
        fresh = J is None or step >= REUSE_JACOBIAN_STEP or it == max_iter
        if fresh:
            J = jacobian(x, r, pb, S, groups)
        a = np.abs(r)
        w = np.where(a <= c, 1.0, c / np.maximum(a, 1e-12))
        JtW = J.T.multiply(w[None, :]).tocsc()
        dx = _normal_step(JtW @ J, -(JtW @ r))
        if not np.all(np.isfinite(dx)):
            raise FloatingPointError("non-finite Gauss-Newton step")
        x = x + dx
        step = float(np.max(np.abs(dx)))
        if step < STEP_TOL:
            if fresh:
                break
            # converged with a reused Jacobian: its fixed point depends on where it was
            # frozen (micrometres along the least observed direction); one step with the
            # Jacobian of this point lands on the problem's own
            step = np.inf
    return x


def _rebase(x: F64, pb: Problem) -> tuple[Problem, F64]:
    """Move the solution into the initial guess (zero pose corrections), keep the rest."""
    R, p, _, _, _ = _unpack(x, pb)
    pb.R0, pb.p0 = R, p
    x_new = x.copy()
    x_new[: 6 * pb.n] = 0.0
    return pb, x_new


def misalignment(x: F64, n: int) -> InsToLidar:
    """The estimated misalignment as :class:`InsToLidar` (``T_ins_base = N @ M^-1``)."""
    lever, bore, lat = x[6 * n : 6 * n + 3], x[6 * n + 3 : 6 * n + 6], float(x[6 * n + 6])
    M = np.eye(4)
    M[:3, :3] = Rotation.from_rotvec(bore).as_matrix()
    M[:3, 3] = lever
    N = InsToLidar.nominal().T_ins_base
    return InsToLidar.from_T(N @ np.linalg.inv(M), latency_s=lat)


#: Measurement blocks whose sigmas are scaled to their own residuals, with their component
#: count (residuals are stacked as (rows, components)), in :func:`residuals`' order.
SCALED_BLOCKS = (
    "odo_t", "odo_r", "ins_p", "ins_r", "rail_lat", "rail_vert", "rail_r", "ground", "ins_v",
    "odo_pair", "gyro", "nh", "accel",
)  # fmt: skip
#: Median of a chi-square variable with one degree of freedom: a robust variance factor
#: of normalised residuals is ``median(r^2) / CHI2_1_MEDIAN``.
CHI2_1_MEDIAN = 0.454936
#: Fewest residual rows a block needs for its variance factor to be estimated.
MIN_ROWS_FOR_SCALE = 6


def measurement_blocks(pb: Problem, x: F64) -> dict[str, F64]:
    """The normalised residuals of each measurement block, (rows, components) each."""
    r = residuals(x, pb)
    out, i = {}, 0
    for name, rows, comps in _block_sizes(pb):
        out[name] = r[i : i + rows * comps].reshape(rows, comps)
        i += rows * comps
    return out


def _block_sizes(pb: Problem) -> list[tuple[str, int, int]]:
    """(name, rows, components) of each measurement block, in the residuals' order."""
    n, m = pb.n, len(pb.ins_k)
    sizes: list[tuple[str, int, int]] = [("odo_t", n - 1, 3), ("odo_r", n - 1, 3)]
    if m:
        sizes += [("ins_p", m, 3), ("ins_r", m, 3)]
    if pb.rail is not None:
        sizes += [("rail_lat", n, 1), ("rail_vert", n, 1), ("rail_r", n, 3)]
    if pb.ground is not None:
        sizes.append(("ground", len(pb.ground["k"]), 3))
    if pb.vel is not None:
        sizes.append(("ins_v", len(pb.vel["k"]), 2))
    if pb.odo_pairs is not None:
        sizes.append(("odo_pair", len(pb.odo_pairs["k"]), ODO_PAIR_COMPONENTS))
    if pb.gyro is not None:
        sizes.append(("gyro", n - 1, 3))
    if pb.nh is not None:
        sizes.append(("nh", n - 1, 2))
    if pb.accel is not None:
        sizes.append(("accel", n - 2, 3))
    return sizes


def redundancy(
    pb: Problem, x: F64, rows: NDArray[np.int64] | None = None
) -> tuple[F64, F64, F64] | None:
    """Per residual row at ``x``: the normalised residual r, its Huber weight w and its
    redundancy number 1 - h (h: the diagonal of the hat matrix W^1/2 J N^-1 J^T W^1/2,
    N = J^T W J). A row the solution can fit exactly has redundancy 0, a row nothing
    depends on 1; they sum to rows - parameters. None when N cannot be factorised.
    ``rows``: compute 1 - h for these rows only (NaN elsewhere; negative indices count
    from the end): the priors' estimates need a few hundred of the thousands of rows,
    and the full diagonal was most of a 100-frame solve's time."""
    r = residuals(x, pb)
    S = _cached_sparsity(pb)
    J = jacobian(x, r, pb, S, _groups(pb))
    a = np.abs(r)
    c = pb.sig.huber
    w = np.where(a <= c, 1.0, c / np.maximum(a, 1e-12))
    N = (J.T.multiply(w[None, :]).tocsc() @ J).toarray()
    N[np.diag_indices_from(N)] += 1e-12 * max(1.0, float(np.max(np.diag(N))))
    try:
        cf = cho_factor(N, check_finite=False)
    except LinAlgError:
        return None
    if rows is None:
        inv = _inverse_from_cholesky(cf)
        if inv is None:
            return None
        return r, w, 1.0 - w * _quadratic_forms(J.tocsr(), inv)
    rows = np.where(rows < 0, rows + len(r), rows)
    Jr = J.tocsr()[rows].toarray()
    one_minus_h = np.full(len(r), np.nan)
    h_rows = w[rows] * np.einsum("ij,ij->i", Jr, cho_solve(cf, Jr.T, check_finite=False).T)
    one_minus_h[rows] = 1.0 - h_rows
    return r, w, one_minus_h


def _inverse_from_cholesky(cf: tuple[F64, bool]) -> F64 | None:
    """(n, n) inverse of the matrix factorised by ``cho_factor`` (LAPACK ``potri``: a third
    of the work of solving against the identity), or None where LAPACK refuses it."""
    c, lower = cf
    inv, info = lapack.dpotri(c, lower=lower)
    if info != 0:
        return None
    tri = np.tril(inv) if lower else np.triu(inv)
    return tri + tri.T - np.diag(np.diag(tri))


def _quadratic_forms(J: csr_matrix, M: F64) -> F64:
    """Per row i of the sparse (m, n) ``J``: ``J_i M J_i^T`` for the dense (n, n) ``M``,
    (m,), from the pairs of each row's nonzeros only (a 100-frame problem: 5180 rows of
    14.5 nonzeros, 1.1 M products against 5.7 M of a dense ``J M``)."""
    nnz = np.diff(J.indptr)
    row_of = np.repeat(np.arange(J.shape[0]), nnz)
    width = nnz[row_of]  # for each nonzero p: its row's nonzero count
    p = np.repeat(np.arange(J.nnz), width)
    first = np.repeat(J.indptr[row_of], width)
    q = first + np.arange(len(p)) - np.repeat(np.cumsum(width) - width, width)
    vals = J.data[p] * J.data[q] * M[J.indices[p], J.indices[q]]
    return np.bincount(row_of[p], weights=vals, minlength=J.shape[0])


def variance_factors(
    pb: Problem, x: F64, red: tuple[F64, F64, F64] | None = None
) -> dict[str, F64]:
    """Per block and component, the factor (>= 1) by which its sigmas understate the scatter
    of its own residuals at solution ``x`` (variance-component estimate).

    With the redundancy numbers (:func:`redundancy`) the factor is Foerstner's
    ``sqrt(sum(w r^2) / sum(1 - h))`` over the component's rows: a block that the solution
    follows closely (ground pairs that alone fix the pitch) has small residuals because it
    has little redundancy, not because it is good; counting its rows instead (the robust
    ``median(r^2)`` estimate, used without redundancy numbers) trusted such blocks as
    designed. A source noisier than its design sigmas (a centreline fitted on a short or
    sparse cloud, a wandering INS, an ICP that slips) then weighs what its residuals say it
    is worth; factors never go below 1 (a block is never trusted more than designed),
    but for the components of :data:`FACTOR_FLOORS`, which go down to their floor.
    Residual rows of zero weight (odometry steps switched off) are left out.
    """
    out: dict[str, F64] = {}
    offsets = _block_offsets(pb)
    for name, res in measurement_blocks(pb, x).items():
        i0 = offsets[name]
        keep = np.ones(len(res), dtype=bool)
        if name in ("odo_t", "odo_r") and len(pb.zupt):
            keep = ~pb.zupt  # zero-velocity steps are not the ICP's
        cur = np.broadcast_to(pb.s(name), (res.shape[1],)).astype(np.float64)
        f = np.ones(res.shape[1])
        for c in range(res.shape[1]):
            rc = res[:, c]
            sel = keep & (rc != 0.0)
            if int(np.sum(sel)) < MIN_ROWS_FOR_SCALE:
                continue
            if red is None:
                f[c] = np.sqrt(np.median(rc[sel] ** 2) / CHI2_1_MEDIAN)
                continue
            rows = i0 + np.flatnonzero(sel) * res.shape[1] + c
            r_all, w_all, red_all = red
            den = float(np.sum(red_all[rows]))
            if den > MIN_BLOCK_REDUNDANCY:
                f[c] = np.sqrt(float(np.sum(w_all[rows] * r_all[rows] ** 2)) / den)
        floor = factor_floors(pb.sig, name, res.shape[1])
        out[name] = np.maximum(cur * np.maximum(f, floor), floor)
    return out


#: Block components whose variance factor may go below 1, each down to the ``Sigmas``
#: field named: {block: {component: field}}. Every other factor stays >= 1.
FACTOR_FLOORS: dict[str, dict[int, str]] = {"odo_pair": {0: "odo_pair_along_floor"}}


def factor_floors(sig: Sigmas, block: str, components: int) -> F64:
    """(components,) the least variance factor of each of ``block``'s components."""
    floor = np.ones(components)
    for c, field_name in FACTOR_FLOORS.get(block, {}).items():
        floor[c] = float(getattr(sig, field_name))
    return floor


#: Least redundancy of a block component for a variance factor from redundancy numbers.
MIN_BLOCK_REDUNDANCY = 1.0


def _block_offsets(pb: Problem) -> dict[str, int]:
    """First residual row of each measurement block (:func:`measurement_blocks`' order)."""
    out, i = {}, 0
    for name, rows, comps in _block_sizes(pb):
        out[name] = i
        i += rows * comps
    return out


#: Rounds of variance-factor estimation and re-solving (each converges in a few steps).
VCE_ROUNDS = 1


def _rescale_and_solve(pb: Problem, x: F64, health: Health) -> F64:
    """Re-solve with each block's sigmas scaled to its residuals until the factors settle,
    then with the INS wander estimated from the solution (:func:`wander_factors`)."""
    for _ in range(VCE_ROUNDS):
        factors = variance_factors(pb, x, redundancy(pb, x) if pb.sig.redundancy_vce else None)
        if all(np.allclose(v, pb.s(k), rtol=0.1) for k, v in factors.items()):
            break
        pb.scale = factors
        x = solve(pb, x, max_iter=4)
    for name, f in pb.scale.items():
        health.metrics[f"fused_variance_factor_{name}"] = float(np.max(f))
    wander = pb.sig.estimate_wander and pb.n_knots >= WANDER_MIN_KNOTS
    motion = pb.sig.estimate_motion and pb.n >= 3
    for _ in range(WANDER_ROUNDS if (wander or motion) else 0):
        red = redundancy(pb, x, _prior_rows(pb, wander, motion))
        if red is None:
            break
        f_wander = wander_factors(pb, x, red) if wander else None
        f_motion = motion_factors(pb, red) if motion else None
        changed = False
        if f_wander is not None and not np.allclose(f_wander, 1.0, rtol=0.1):
            _set_bias_step(pb, pb.bias_step_sigma * f_wander)
            changed = True
        if f_motion is not None and not np.allclose(f_motion, 1.0, rtol=0.1):
            total = np.clip(pb.s("rot_acc") * f_motion, *MOTION_FACTOR_TOTAL)
            pb.scale["rot_acc"] = total
            changed = True
        if not changed:
            break
        x = solve(pb, x, max_iter=4)
    if wander:
        for name, q in zip(WANDER_NAMES, pb.bias_step_sigma, strict=True):
            unit = np.degrees(q) if name in WANDER_NAMES[:3] else q
            health.metrics[f"fused_ins_wander_estimated_{name}"] = float(unit)
    if motion:
        sig_r = np.asarray(pb.sig.rot_acc) * np.broadcast_to(pb.s("rot_acc"), (3,))
        for axis, q in zip(("roll", "pitch", "heading"), sig_r, strict=True):
            health.metrics[f"fused_rotation_acceleration_{axis}_mdeg"] = float(1000 * np.degrees(q))
    return x


#: Rounds of the wander estimate (each: redundancy numbers, then a re-solve).
WANDER_ROUNDS = 3
#: Fewest INS bias knots for a wander estimate (its steps are its samples).
WANDER_MIN_KNOTS = 4
#: Bounds of one round's factor (a round moves a sigma by at most this much).
WANDER_FACTOR_BOUNDS = (0.2, 5.0)
#: The bias-step components estimated from the solution: the heading only. Roll and pitch
#: keep the three-cornered hat with the ground pairs (:func:`_ins_level_wander`): estimated
#: from the solution, a ground pair's systematic roll error read as INS wander (fire_site,
#: 60 frames, good INS: roll over 30 frames 6.8 -> 21.8 mdeg); the positions keep their
#: measure against the odometry (the INS speed and the odometry pairs carry the steps).
WANDER_ESTIMATED = (False, False, True, False, False, False)
#: Least redundancy (sum of 1 - h over a component's prior rows) to estimate its factor.
WANDER_MIN_REDUNDANCY = 0.5
#: The bias-step components, in :attr:`Problem.bias_step_sigma`'s order.
WANDER_NAMES = ("roll_deg", "pitch_deg", "heading_deg", "east_m", "north_m", "up_m")


def _set_bias_step(pb: Problem, q: F64) -> None:
    """Take the INS wander sigmas ``q`` (6,), clipped to the floors, and rebuild what
    depends on them (the attitude records' sigmas: the wander between knots)."""
    a_cap = pb.sig.att_bias_step[2]
    p_cap = pb.sig.pos_bias_step[2]
    q = q.copy()
    q[:3] = np.clip(q[:3], WANDER_FLOOR_R, a_cap)
    q[3:] = np.clip(q[3:], WANDER_FLOOR_P, p_cap)
    pb.bias_step_sigma = q
    pb.ins_r_share = _ins_attitude_factors(pb.ins_k, pb.sig, q, pb.ins_white)


#: Floors of an estimated INS wander per knot spacing (rad, m): below what a survey-grade
#: INS's filter holds, sampling luck on a short sequence must not make it absolute.
WANDER_FLOOR_R = 0.001 * DEG
WANDER_FLOOR_P = 0.002


def wander_factors(pb: Problem, x: F64, red: tuple[F64, F64, F64] | None = None) -> F64 | None:
    """(6,) factors on the INS wander sigmas (the bias-step prior), by variance-component
    estimation with redundancy numbers (Foerstner): for the prior's rows of component c,
    ``f_c^2 = sum(w r^2) / sum(1 - h)`` with r the normalised residuals, w the Huber
    weights and h the diagonal of the hat matrix ``W^1/2 J N^-1 J^T W^1/2``.

    The INS's wander is what no single source measures: against the odometry alone the
    odometry's own drift counts as the INS's (a good INS's heading wander measured 0.02 deg
    a second where it had none). Here every source weighs in (odometry steps and pairs,
    ground pairs, rails, INS positions and attitude): the bias steps the solution needs,
    against the freedom the prior gave them, say how much the INS wandered. None when the
    normal matrix cannot be inverted or the prior has no redundancy. ``red``: the
    redundancy numbers at ``x`` when already computed.
    """
    red = red if red is not None else redundancy(pb, x)
    if red is None:
        return None
    r, w, one_minus_h = red
    n_steps = (pb.n_knots - 1) * 6
    rows = np.arange(len(r) - n_steps, len(r))
    rb = (w[rows] * r[rows] ** 2).reshape(-1, 6)
    num, den = rb.sum(axis=0), one_minus_h[rows].reshape(-1, 6).sum(axis=0)
    log.debug("wander VCE: sum w r^2 %s, redundancy %s", num, den)
    # a component whose prior has (almost) no redundancy is left as it is
    f = np.where(den > WANDER_MIN_REDUNDANCY, np.sqrt(num / np.maximum(den, 1e-12)), 1.0)
    f[~np.asarray(WANDER_ESTIMATED)] = 1.0
    return np.clip(f, *WANDER_FACTOR_BOUNDS)


#: Bounds of the rotation smoothness prior's total factor (on ``Sigmas.rot_acc``): a
#: sequence's own motion decides how smooth its rotations are, within 0.1x (2 mdeg per
#: frame^2 at the default: a clothoid's yaw acceleration at 20 m/s is about 13) and 3x.
MOTION_FACTOR_TOTAL = (0.1, 3.0)
#: Least redundancy of a rotation axis' smoothness rows to estimate its factor.
MOTION_MIN_REDUNDANCY = 2.0


def _prior_rows(pb: Problem, wander: bool, motion: bool) -> NDArray[np.int64]:
    """Residual rows whose redundancy the prior estimates read: the INS bias steps (the
    last rows, as negative indices) and the rotation smoothness rows."""
    out = []
    if wander:  # counted from the end (negative): the last rows
        out.append(np.arange(-(pb.n_knots - 1) * 6, 0))
    if motion:
        i0 = _smoothness_offset(pb)
        out.append(np.arange(i0, i0 + 3 * (pb.n - 2)))
    return np.concatenate(out) if out else np.zeros(0, dtype=np.int64)


def _smoothness_offset(pb: Problem) -> int:
    """First residual row of the rotation smoothness prior (after the measurement blocks
    and the positions' second differences)."""
    return sum(rows * comps for _, rows, comps in _block_sizes(pb)) + 3 * (pb.n - 2)


def motion_factors(pb: Problem, red: tuple[F64, F64, F64]) -> F64 | None:
    """(3,) factors on the rotation smoothness sigmas (roll, pitch, heading), by the same
    variance-component estimate as :func:`wander_factors`, on the rows of the second
    differences of the frame-to-frame rotations.

    How smoothly a train turns is the sequence's own: a straight or constant curve has
    almost no yaw acceleration, a clothoid entered at speed has a steady one, a coach's
    body sways in roll and pitch on its suspension. A fixed prior either leaves the
    odometry's per-frame heading noise in the poses (jitter of the placed object) or
    flattens a real transition; estimated from the solution, each axis takes the
    smoothness its residuals show against the freedom the prior gives them. None when no
    axis has enough redundancy.
    """
    r, w, one_minus_h = red
    i0 = _smoothness_offset(pb)
    rows = np.arange(i0, i0 + 3 * (pb.n - 2))
    rb = (w[rows] * r[rows] ** 2).reshape(-1, 3)
    num, den = rb.sum(axis=0), one_minus_h[rows].reshape(-1, 3).sum(axis=0)
    if not np.any(den > MOTION_MIN_REDUNDANCY):
        return None
    return np.where(den > MOTION_MIN_REDUNDANCY, np.sqrt(num / np.maximum(den, 1e-12)), 1.0)


def _with_scan_errors(pb: Problem, J: csc_matrix, w: F64) -> tuple[csc_matrix, F64]:
    """The odometry steps as differences of per-scan errors (:mod:`.scan_errors`)."""
    n = pb.n
    if n < 2:
        return J, w
    offs = _block_offsets(pb)
    rows = np.arange(3 * (n - 1)).reshape(n - 1, 3)
    a_t = pb.w_odo_t / pb.s_odo("odo_t")
    a_r = pb.w_odo_r / pb.s_odo("odo_r")
    # a registration of its own at full weight, along the track too: a step the odometry
    # was unsure of drifts as it goes
    use = full_weight_steps(pb.w_odo_t, pb.w_odo_r, pb.zupt, pb.sig.odo_t, along=True)
    return with_scan_errors(
        J, w, offs["odo_t"] + rows, np.broadcast_to(a_t, (n - 1, 3)),
        offs["odo_r"] + rows, np.broadcast_to(a_r, (n - 1, 3)), use, pb.sig.odo_drift_share,
    )  # fmt: skip


def information(pb: Problem, x: F64) -> PoseInformation:
    """The solution's information matrix J^T W J (Huber weights at ``x``; frame k's
    columns are its rotation vector then position, as :class:`PoseInformation` has them)
    and its variance factor: the robust chi-square scale of the measurements' normalised
    residuals (not the priors'), at least 1 (a solution whose residuals spread more than
    their sigmas is less certain than its information says). The odometry steps count as
    differences of per-scan errors (:mod:`.scan_errors`, ``Sigmas.odo_drift_share``): per-
    scan error columns follow the problem's own, marginalised with them."""
    r = residuals(x, pb)
    S = _cached_sparsity(pb)
    J = jacobian(x, r, pb, S, _groups(pb))
    a = np.abs(r)
    c = pb.sig.huber
    w = np.where(a <= c, 1.0, c / np.maximum(a, 1e-12))
    if pb.odo_pairs is not None:
        # KISS-ICP's pairs (along, lateral, heading) are its poses' differences, the sums
        # of its steps: they shape the estimate but are no new information. The fine pairs
        # (third column) are registrations of their own, scan against scan: they are.
        i0 = _block_offsets(pb)["odo_pair"]
        q = np.arange(len(pb.odo_pairs["k"]))
        kiss = np.array([0, 1, 3])
        w[(i0 + ODO_PAIR_COMPONENTS * q[:, None] + kiss).ravel()] = 0.0
    J, w = _with_scan_errors(pb, J, w)
    A = (J.T.multiply(w[None, :]).tocsc() @ J).tocsc()
    meas = np.concatenate([b.ravel() for b in measurement_blocks(pb, x).values()])
    meas = meas[meas != 0.0]
    scale = max(1.0, float(np.median(meas**2) / CHI2_1_MEDIAN)) if len(meas) else 1.0
    return PoseInformation(A, pb.n, scale)


def _block_rms(pb: Problem, x: F64) -> dict[str, float]:
    """RMS (in sigmas) of the residual blocks, for health metrics."""
    r = residuals(x, pb)
    n, m = pb.n, len(pb.ins_k)
    sizes = [("odo", 6 * (n - 1)), ("ins", 6 * m)]
    if pb.rail is not None:
        sizes.append(("rails", 5 * n))
    out, i = {}, 0
    for name, size in sizes:
        seg = r[i : i + size]
        out[f"fused_rms_{name}"] = float(np.sqrt(np.mean(seg**2))) if size else 0.0
        i += size
    if pb.rail is not None:
        out["fused_rail_frames_sharing_median"] = pb.rail["frames_sharing"]
        for axis, sigma in zip(("roll", "pitch", "heading"), pb.rail["sigma_r_base"], strict=True):
            out[f"fused_rail_sigma_{axis}_deg"] = float(np.degrees(sigma))
    return out


class FusedStrategy:
    """Least-squares smoothing of odometry, INS and the rail constraint."""

    name = "fused"

    def __init__(self, sigmas: Sigmas | None = None) -> None:
        self.sigmas = sigmas or Sigmas()

    def run(self, inp: LocalizationInput) -> LocalizationResult:
        started = time.perf_counter()
        health = Health()
        try:
            pb = build_problem(inp, health, self.sigmas)
            x = solve(pb)
            if pb.rail is not None and inp.ego is not None:
                pb, x = _rebase(x, pb)
                R, p, _, _, _ = _unpack(x, pb)
                pb.rail = _linearise_rails(inp.ego, p, R, pb.sig)
                x = solve(pb, x, max_iter=4)
            x = _rescale_and_solve(pb, x, health)
        except Exception as exc:
            log.exception("fused smoothing failed")
            return self._fallback(inp, health, started, f"smoothing failed ({exc})")
        R, p, _, _, _ = _unpack(x, pb)
        T = poses_from(R, p)
        if not np.all(np.isfinite(T)):
            return self._fallback(inp, health, started, "non-finite solution")
        cal = misalignment(x, pb.n)
        health.metrics.update(_block_rms(pb, x))
        knots = _bias_knots_of(x, pb)
        health.metrics["fused_ins_attitude_bias_max_deg"] = float(
            np.degrees(np.max(np.linalg.norm(knots[:, :3], axis=1)))
        )
        health.metrics["fused_ins_position_bias_max_m"] = float(
            np.max(np.linalg.norm(knots[:, 3:], axis=1))
        )
        if pb.gyro is not None:
            i0 = _gyro_bias_col(pb.n, pb.n_knots)
            for axis, b in zip(("roll", "pitch", "heading"), x[i0 : i0 + 3], strict=True):
                health.metrics[f"fused_gyro_bias_{axis}_deg_h"] = float(np.degrees(b) * 3600.0)
        if pb.n_acc_knots:
            acc = np.mean(_acc_bias_knots_of(x, pb), axis=0) / 9.80665e-3
            for axis, b in zip(("along", "lateral", "vertical"), acc, strict=True):
                health.metrics[f"fused_accel_bias_{axis}_mg"] = float(b)
        if "cloud_pitch" in _extra_cols(pb):
            health.metrics["fused_cloud_pitch_mrad"] = 1000.0 * _cloud_pitch_of(x, pb)
        if "ground_tilt" in _extra_cols(pb):
            drift = 1e3 * math.degrees(_ground_tilt_of(x, pb))
            health.metrics["fused_ground_tilt_roll_mdeg_per_m"] = drift
        if "ground_pitch" in _extra_cols(pb):
            drift = 1e3 * math.degrees(_ground_pitch_drift_of(x, pb))
            health.metrics["fused_ground_pitch_drift_mdeg_per_m"] = drift
        notes = self._observability(inp, pb, health)
        info = information(pb, x)
        health.metrics["fused_variance_factor_global"] = info.scale
        return make_result(
            self.name,
            inp,
            T,
            health,
            started,
            extras={"ins_to_lidar": cal.to_json(), "observability": notes},
            information=info,
        )

    @staticmethod
    def _observability(inp: LocalizationInput, pb: Problem, health: Health) -> list[str]:
        notes = [
            "along-track position from the INS as is: the along-track lever arm and the "
            "latency times the speed are unobservable; latency from the attitude lag only"
        ]
        ins = inp.options.get("_ins_frames")
        if isinstance(ins, InsFrames) and ins.standstill:
            health.warn(
                "fused: standstill, INS-to-lidar misalignment unobservable beyond what the "
                "rails fix; priors kept"
            )
            notes.append("standstill: misalignment from priors (and rails) only")
        if pb.rail is None:
            notes.append("no rails: misalignment kept at the nominal assumption (unobservable)")
        return notes

    def _fallback(
        self, inp: LocalizationInput, health: Health, started: float, why: str
    ) -> LocalizationResult:

        fallback = RailsStrategy().run(inp)
        health.degrade(f"fused: {why}; falling back to {fallback.health.fallback or 'rails'}")
        health.fallback = fallback.health.fallback or "rails"
        return make_result(self.name, inp, fallback.track.T, health, started)


def fused_track(inp: LocalizationInput) -> PoseTrack:
    """Convenience: the fused poses only."""
    return FusedStrategy().run(inp).track
