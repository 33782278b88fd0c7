"""The geometry core: the one camera model, rigid transforms and quaternions, pose tracks
and geodesy, on float64 arrays. Rendering, preparation, augmentation and evaluation all
import it; it imports nothing else of the project.
"""
