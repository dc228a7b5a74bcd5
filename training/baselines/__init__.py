"""The paper's comparison families (its section 3.1), conditioned on the same nu and trained on
the same standard data with the cGAN's trainer: a voxel GAN (3D-GAN family), a direct point-cloud
GAN (r-GAN family) and a point-cloud diffusion model (DPM family). Their family objects, which the
trainer, export and evaluation talk to, are in ``training/families.py``."""
