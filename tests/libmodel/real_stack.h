// The real arm crop (data-samples/real) as a stack of misregistered slices:
// each slice the crop (or a window of it) shifted by a whole number of
// pixels, edges replicated. For tests that need what real, unregistered
// cryosection slices do to segmentation and surfaces.
#pragma once

#include "libmodel/segment/segment.h"

#include <algorithm>
#include <array>
#include <filesystem>
#include <string>
#include <vector>

namespace orthosim::test {

// Shifts (dx, dy) in pixels, 1-2 px a slice, of the SegmentReal stack.
inline const std::vector<std::array<int, 2>>& arm_crop_shifts() {
  static const std::vector<std::array<int, 2>> s{{0, 0}, {1, -1}, {2, 1}, {-1, 2}, {-2, 0}, {0, -2}, {1, 2}, {-1, -1}};
  return s;
}

// Writes dir/s0.png, s1.png, ...: the crop shifted by each of `shifts`, then
// cut to the window [x0, x0 + nx) x [y0, y0 + ny) (nx, ny <= 0: the whole crop).
inline void write_shifted_arm_crop(const std::filesystem::path& dir, const std::vector<std::array<int, 2>>& shifts,
                                   int x0 = 0, int y0 = 0, int nx = 0, int ny = 0) {
  const RgbImage crop = read_slice(std::string(ORTHOSIM_SOURCE_DIR) + "/data-samples/real/vhp-f-1432a-arm.png");
  if (nx <= 0) x0 = 0, nx = crop.nx;
  if (ny <= 0) y0 = 0, ny = crop.ny;
  for (std::size_t z = 0; z < shifts.size(); ++z) {
    RgbImage s;
    s.nx = nx, s.ny = ny;
    s.rgb.resize(static_cast<std::size_t>(nx) * ny * 3);
    for (int y = 0; y < ny; ++y)
      for (int x = 0; x < nx; ++x) {
        const int sx = std::clamp(x0 + x - shifts[z][0], 0, crop.nx - 1);
        const int sy = std::clamp(y0 + y - shifts[z][1], 0, crop.ny - 1);
        for (int c = 0; c < 3; ++c)
          s.rgb[static_cast<std::size_t>((y * nx + x) * 3 + c)] = crop.rgb[static_cast<std::size_t>((sy * crop.nx + sx) * 3 + c)];
      }
    std::string name = std::to_string(z);  // (GCC 12 warns -Wrestrict, falsely, on "s" + to_string(z))
    name.insert(0, 1, 's');
    name += ".png";
    write_png((dir / name).string(), s);
  }
}

}  // namespace orthosim::test
