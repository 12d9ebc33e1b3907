"""``toyfog``: a method outside the package, as small as a method gets (the example of
docs/architecture.md): every view segment in the medium scatters ``level`` times its
length, in rgb, times the segment's weight. One module and one ``.cl`` file beside it;
nothing in clscatter names it."""
from pathlib import Path

from clscatter.device import add_kernel_dir
from clscatter.methods import AutoRole, Method, Param, PassResult, register

add_kernel_dir(Path(__file__).parent)          # toyfog.cl lives beside this module


@register
class ToyFog(Method):
    """``toyfog``: constant radiance per unit length along every view segment."""

    NAME = "toyfog"
    PARAMS = (Param("level", 0.5, "radiance per unit length (normalised units)", lo=0.0),)
    TERMS = frozenset({"direct"})                  # what it computes when run alone
    AUTO = {"direct": AutoRole(priority=1000)}     # auto prefers it for direct light

    def render(self, ctx) -> PassResult:
        if len(ctx.paths) == 0:
            return PassResult(medium=ctx.zeros())
        segs = ctx.segments()                      # sorted, on the device
        out = ctx.scratch(16 * segs.count)         # one float4 per segment, freed after
        ctx.call("toyfog", "toyfog", segs.count, segs=segs.buf, n=segs.count,
                 level=self.params["level"], out=out)
        return PassResult(medium=segs.accumulate(out))
