"""The fused rasterizer's tuning constants: tile sides, face blocks, splits, warps, register caps and memory
bounds. None changes an image or a gradient beyond float rounding order; each trades launch shape against
work per program. :mod:`.rasterize` reads them when it launches, so a benchmark may set them between renders
(``fused.tuning.BWD_SUB_BLOCK = 64``). The same-call A/B timings behind the splits, the backward tiles and
the register cap are in BENCHMARKS.md, section 2.1 ("The fused constants' defaults"); those of the walks at a
population's batch in section 2.5.
"""

#: Forward: pixels per tile side and faces per block. A forward program evaluates a block's faces at all its
#: pixels as one (FACE_BLOCK, TILE^2) array: 4 x 4 pixels and 64 faces make 1,024 pairs, 8 per thread of 4
#: warps. A smaller tile skips more blocks by their boxes but reads each block's coefficients for fewer
#: pixels; a larger one the reverse. Powers of two (``rasterize_fused`` takes others per call).
TILE = 4
FACE_BLOCK = 64
#: Face blocks per super-block: the coarse level of the kernels' walk over the faces (see
#: :func:`.reference.super_block_boxes`). One box test skips SUPER_BLOCK x FACE_BLOCK faces, so a program far
#: from a detailed mesh pays O(F / 1024) tests instead of O(F / 64).
SUPER_BLOCK = 16
#: Faces the forward evaluates at once (a block in parts of this many; <= FACE_BLOCK) and its warps (None: 4,
#: or 8 for more than 1024 face-pixel pairs at once).
FWD_SUB_BLOCK = 64
FWD_WARPS: int | None = None
#: Whether the forward evaluates, of each block whose box reaches its tile, only the faces whose own boxes
#: reach it, packed in face order into chunks of FWD_SUB_BLOCK (a rank by prefix sum, then a gather of their
#: coefficients). The block's box is the union of 64 faces' boxes, so most of a block's faces are far from most
#: tiles it reaches (benchmarks/forward_walk.py counts the pairs each walk evaluates). The same image (the faces
#: come in the same order; the soft models' sums are regrouped: float rounding). Off: on a GPU the rank and
#: gather cost more than the pairs they save (BENCHMARKS.md section 2.5).
FWD_COMPACT = False
#: Whether the hard model's forward walk, in renders without gradient (nothing saved: decoupled rollouts,
#: evaluation, videos), finds each pixel's face by depth alone and shades only that face at the end, instead of
#: interpolating normal and albedo and shading every face-pixel pair it meets (over half of a pair's
#: arithmetic). The same face at the same depth, bit for bit, and the same colour to a few units in the last
#: place (the compiler may contract the shading's multiply-adds differently in the two walks; bit for bit under
#: Triton's interpreter: tests/diffrender/test_fused.py). A render that keeps its blend state for a backward
#: shades every pair whatever this says: there the deferred walk timed slower (BENCHMARKS.md section 2.5). The
#: soft models shade every pair they blend.
FWD_DEFER_SHADING = True
#: Whether every render bins its faces once per chunk of environments before the forward walks (off by default). A
#: binning kernel (``forward._bin_faces``, one program per forward tile of TILE x TILE pixels and environment) lists,
#: for each tile, the faces whose boxes (the setup kernel's ``face_box``) reach the tile's pixel centres, in face order,
#: into a fixed-capacity list (B, T, BIN_CAPACITY) int32 with each tile's count (B, T) (T tiles in row-major order);
#: every forward walk (hard, softmax and alpha, with the blend state kept or not, and the backward's recompute of the
#: state) then evaluates only its tile's listed faces, in chunks of FWD_SUB_BLOCK. A tile with more than BIN_CAPACITY
#: such faces walks the blocks instead, on the device (the same image), and counts itself in a device counter that
#: :func:`.rasterize.bin_overflows` reads outside any CUDA graph (one warning, ``BinOverflowWarning``; the trainer reads
#: it after each iteration's synchronising transfer and logs a nonzero count as the metrics key ``bin_overflows``). The
#: same faces in the same order: the hard model's face, depth and image bit for bit, the soft models' sums regrouped
#: (float rounding). The lists are transients of the forward (4 x T x BIN_CAPACITY bytes an environment), never saved
#: for the backward, whose walk keeps its own packing (BWD_COMPACT) at its own tile (BWD_TILE). BIN_CAPACITY is a
#: compile-time constant: fixed before any capture (:func:`.rasterize.bin_capacity_needed` measures a frame's busiest
#: tile). With binning, a tile's walk is split between at most ceil(BIN_CAPACITY / FWD_SUB_BLOCK) programs (split s
#: takes list chunks s, s + S, ...).
FWD_BIN = False
BIN_CAPACITY = 256
#: The forward's walk over the super-blocks is split between up to FWD_MAX_SPLITS programs per tile (program s
#: takes super-blocks s, s + S, ...), one per FWD_SPLIT_SUPER_BLOCKS super-blocks (see
#: :func:`.rasterize.forward_splits`): the few tiles where a detailed mesh crowds thousands of faces would
#: otherwise finish long after the rest. The parts are merged by a second kernel over MERGE_BLOCK pixels per
#: program, as the backward's per-pixel kernel, so a split forward pays a launch and a round trip of
#: PART_PER_PIXEL numbers per pixel and split: worth it only for many super-blocks, hence 4 per split.
FWD_MAX_SPLITS = 8
FWD_SPLIT_SUPER_BLOCKS = 4
MERGE_BLOCK = 256
#: Numbers the split forward's parts may hold at once (fewer splits for large batches or images): bounds the
#: transient (splits, B, PART_PER_PIXEL, H, W) to 2^27 numbers, a quarter of the coefficients' bound.
PART_ELEMS = 1 << 27
#: Backward: tile side [px] (its own: it reads the forward's per-pixel state, not its tiling), faces per
#: sub-block and warps (None: one warp per 32 faces). A backward program keeps one face per lane, with its 45
#: coefficients and 45 gradient accumulators in registers, and walks the tile's pixels inside the sub-block's
#: face boxes; each face then issues one atomic add per coefficient and tile. A face straddles fewer 8 x 8
#: tiles than 4 x 4 ones (fewer atomics), at the price of more pixels walked per program. A sub-block of 32
#: faces is one warp's pixel walk; with BWD_COMPACT (below) it holds only faces that reach the tile.
BWD_TILE = 8
BWD_SUB_BLOCK = 32
BWD_WARPS: int | None = None
#: Whether a backward program's lanes hold, of each block whose box reaches its tile, only the faces whose own
#: boxes reach it, packed in face order into sub-blocks of BWD_SUB_BLOCK (as the forward's FWD_COMPACT), so that
#: no lane walks the tile's pixels for a face far from it (benchmarks/forward_walk.py counts the lane-pixels).
#: Each face's gradient is the same sum over the same pixels in the same order. On by its GPU timing
#: (BENCHMARKS.md section 2.5), though the gather's (FACE_BLOCK, 32) selection makes the soft backward spill
#: (benchmarks/fused_ptx.py compiles it); a gather through a per-program scratch row would avoid that.
BWD_COMPACT = True
#: Where faces crowd (more than DENSE_FACES_PER_PIXEL per image pixel), the backward's tile side [px] (see
#: :func:`.rasterize.backward_tile`): a smaller tile shares the busiest tiles' pairs among more programs. Equal
#: to BWD_TILE by default: where the backward's walk is split (below), the split already shares those pairs
#: out, and a smaller tile only adds atomics; the knob stays for scenes whose faces crowd fewer tiles.
BWD_TILE_DENSE = 8
DENSE_FACES_PER_PIXEL = 1.0
#: The backward's walk over the super-blocks is split between up to BWD_MAX_SPLITS programs per tile, one per
#: BWD_SPLIT_SUPER_BLOCKS super-blocks (see :func:`.rasterize.backward_splits`). Each face's gradient is a sum
#: over tiles anyway (atomic adds), so a split costs no merge, only the super-block tests each program repeats:
#: hence finer (2 per split) and wider (16) than the forward's.
BWD_MAX_SPLITS = 16
BWD_SPLIT_SUPER_BLOCKS = 2
#: Registers per thread the forward kernel and the soft and hard models' backward kernels may use (None: the
#: compiler's choice, 255 for the backward kernels, so that only 8 warps fit on a multiprocessor). Capped, more
#: programs share a multiprocessor at the cost of spills: the soft backward, whose every pixel keeps many
#: pairs, gains; the hard backward (one pair per pixel) and the forward lose.
FWD_MAXNREG: int | None = None
BWD_MAXNREG: int | None = 128
BWD_MAXNREG_HARD: int | None = None
#: Per-face coefficients held at once: environments are rendered in chunks of at most this many, which bounds
#: the renderer's working set at any face count. Every chunk is a kernel launch whose time is at least that of
#: its busiest tile, plus a few hundred setup kernels, so the bound is as large as memory allows: 2^29 numbers
#: hold 64 images of 100k faces in one chunk (64 x 100,736 x 45 x 4 bytes = 1.2 GB at float32; peak memory in
#: BENCHMARKS.md, section 2.1).
COEF_ELEMS = 1 << 29
