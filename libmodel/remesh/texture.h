// Texture of a remeshed surface from the colour cryosection stack, and the
// viewer exports: OBJ (quads) + MTL + PNG, and glTF 2.0 (assimp).
#pragma once

#include "libmodel/remesh/remesh.h"

#include <array>
#include <cstdint>
#include <string>
#include <vector>

namespace orthosim {

// The colour stack: slice k is the image at z = origin_m[2] + k * spacing_m[2];
// pixel (column x, row y) is at origin_m + (x, y, k) * spacing_m (the frame of
// libmodel/format/model.h).
struct ColourStack {
  std::vector<std::string> files;  // one per slice, in name order
  int nx = 0, ny = 0;              // image width and height (pixels)
  std::array<double, 3> spacing_m{1e-3, 1e-3, 1e-3};
  std::array<double, 3> origin_m{0, 0, 0};
  // px (x, y) each slice is moved by before sampling (segment --register's
  // /volume/slice_shift_px); empty: none
  std::vector<std::array<int, 2>> shift;
  // Slices are read as segment reads them (read_slice): 16-bit ones scaled
  // from bit_depth significant bits (segment's --bit-depth), no EXIF rotation.
  int bit_depth = 16;
  // The part of each slice read (x, y, w, h px; w = h = 0: the whole slice):
  // samples beyond it are taken at its edge and counted as outside. Only
  // without shifts (a moved slice is read whole).
  std::array<int, 4> region{0, 0, 0, 0};
};

// Lists DIR/slices/* (or DIR/* when DIR has no slices/ folder) as segment
// does (list_stack: its image extensions, hidden files left out, natural name
// order: s2 before s10), and reads the first slice for the image size
// (read_slice: a corrupt or grey first slice throws as in segment). Throws Error(dir, ...) when there is no
// slice, or spacing is not positive.
ColourStack open_colour_stack(const std::string& dir, const std::array<double, 3>& spacing_m,
                              const std::array<double, 3>& origin_m);

struct TextureOptions {
  double texel_m = 0;     // texel size (m); 0: the smallest in-plane voxel size
  int max_size = 4096;    // largest width or height in texels, in [16, 16384]
  double depth_m = -1;    // sample this far inside the surface (m); < 0: one in-plane voxel
  int cache_slices = 32;  // slices kept in memory, >= 2
};

struct TextureImage {
  int width = 0, height = 0;
  std::vector<std::uint8_t> rgb;  // height * width * 3, row-major, RGB; row 0 is the start of the axis (v = 0)
  std::int64_t outside = 0;       // texels whose sample point fell outside the stack or its region read (clamped)
  std::int64_t side_loops = 0;    // loops beside the tube's own in the texel rows' planes, left out (noise)
};

// Texel (a, b) holds the stack colour (trilinear) at the surface point at arc
// fraction u = (a + 0.5) / width around the ring at s = (b + 0.5) / height *
// length, moved depth_m inside: the same (u, v = s / length) as the uv of the
// grid vertices (with the remesh's `around` and `arc_window`), so the texture
// is exact whatever the grid size. Throws
// Error(slice file, ...) when a slice cannot be read or has another size.
TextureImage bake_texture(const Surface& outer, const TubeSweep& sweep, RingSampling around, int arc_window, const ColourStack& stack,
                          const TextureOptions& o, const std::string& name);

// Writes a PNG (atomically).
void write_texture_png(const std::string& path, const TextureImage& t);

// Wavefront OBJ with the grid's quads: v (nu*nv), vt ((nu+1)*nv: the seam
// column repeats with u = 1), f v/vt. OBJ's vt origin is the bottom left, so
// vt = (u, 1 - v). With `mtl_file`, adds mtllib/usemtl `material`.
void write_quad_obj(const std::string& path, const QuadSurface& q, const std::string& mtl_file = "",
                    const std::string& material = "");
void write_mtl(const std::string& path, const std::string& material, const std::string& texture_file);

// glTF 2.0 (JSON + .bin beside it) through assimp: quads split into two
// triangles, the seam column duplicated, texture_file (may be empty) as the
// base colour. Throws Error(path, ...) when the exporter fails.
void write_gltf(const std::string& path, const QuadSurface& q, const std::string& texture_file, const std::string& name);

}  // namespace orthosim
