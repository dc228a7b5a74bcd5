"""How an APCG+ network draws its sheet from its last features (``PlusConfig.head``,
apcg_core/nn/apcg_plus.py; SPEC section 7a): ``conv``, a 3 x 3 convolution over features at the
sheet's resolution; ``upconv``, the last transposed convolution draws the sheet itself. Its own
torch-free module, below both the runtime family and the torch network, so the command line can
offer the choice without loading torch and neither of them imports the other."""

HEADS = ("conv", "upconv")

__all__ = ["HEADS"]
