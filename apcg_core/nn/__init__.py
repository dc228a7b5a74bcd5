"""The improved cGAN of the paper (SPEC section 7). Importing this package imports torch."""

from .models import Discriminator, Generator, NetConfig, SelfAttention

__all__ = ["Discriminator", "Generator", "NetConfig", "SelfAttention"]
