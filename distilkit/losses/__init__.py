"""Distillation objectives as plain differentiable functions: tensors in, scalar tensor out.

>>> import torch, distilkit.losses as L
>>> L.dskd(torch.randn(100, 32), torch.randn(100, 32))   # SCPNet eq. 1-2
>>> L.scene_wise(torch.randn(500, 3), torch.randn(5000, 3))   # ScoreLiDAR eq. 12

Class/channel dimension is 1 for dense maps; ``mask`` arguments are bool tensors shaped like the
map without its class dimension.
"""

from distilkit.losses.bev import bev_from_voxels, collapse_height, column_weights
from distilkit.losses.ce import weighted_cross_entropy
from distilkit.losses.cleaners import cleaners
from distilkit.losses.dpo import distillation_dpo
from distilkit.losses.dskd import dskd
from distilkit.losses.feature import fitnet, nst, pkt
from distilkit.losses.hardness import (geometry_weighted_ce, hard_voxel_ce, local_geometric_anisotropy,
                                      sample_hard_voxels, voxel_sample)
from distilkit.losses.hassc import hassc_kd, teacher_batch_miou
from distilkit.losses.l2cocc import l2cocc_fsd, l2cocc_pad, l2cocc_relation
from distilkit.losses.licrocc import licrocc_affinity, licrocc_bev, licrocc_kl
from distilkit.losses.logit import dist, kd
from distilkit.losses.mgd import mgd
from distilkit.losses.monoocc import monoocc_image, monoocc_kl
from distilkit.losses.proposal import depth_l1, occupancy_ce
from distilkit.losses.pvkd import pvkd, pvkd_affinity, supervoxel_ids, supervoxel_radial_bin
from distilkit.losses.rgo2d import rgo2d, rgo2d_region
from distilkit.losses.segmentation import cross_entropy, lovasz_softmax
from distilkit.losses.ssc import geo_scal, log_frequency_weights, partial_ce, sem_scal, weighted_ce
from distilkit.losses.structural import curvature, point_wise, scene_wise, select_keypoints, structural
from distilkit.losses.vsd import vsd

__all__ = ["dskd", "kd", "fitnet", "pkt", "nst", "dist", "pvkd", "pvkd_affinity", "supervoxel_ids", "mgd", "cleaners",
           "rgo2d_region", "rgo2d", "cross_entropy", "lovasz_softmax", "vsd", "scene_wise", "point_wise", "curvature",
           "select_keypoints", "structural", "weighted_ce", "partial_ce", "geo_scal", "sem_scal", "log_frequency_weights",
           "depth_l1", "occupancy_ce", "distillation_dpo", "hassc_kd", "teacher_batch_miou", "l2cocc_pad", "l2cocc_fsd",
           "l2cocc_relation", "local_geometric_anisotropy", "geometry_weighted_ce", "sample_hard_voxels",
           "hard_voxel_ce", "voxel_sample", "weighted_cross_entropy", "supervoxel_radial_bin", "licrocc_kl", "licrocc_bev",
           "licrocc_affinity", "monoocc_kl", "monoocc_image", "bev_from_voxels", "collapse_height", "column_weights"]
