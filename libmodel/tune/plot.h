// The stress-strain picture of a tuned tissue (orthosim tune --plot;
// docs/tune.md): the target law, the achieved fit, the measured curve of the
// virtual experiment at the tuned parameters and the untuned rule's curve.
#pragma once

#include "libmodel/tune/tune.h"

#include <string>

namespace orthosim::tune {

struct PlotOptions {
  int width_px = 800, height_px = 560;  // image size, >= 200 x 150
  std::string title;                    // e.g. the tissue's name
};

// Writes a PNG (stress in kPa against nominal strain). Throws Error(path, ...)
// if the image cannot be written or the result holds no curve.
void write_curve_png(const std::string& path, const TuneResult& result, const PlotOptions& options = {});

}  // namespace orthosim::tune
