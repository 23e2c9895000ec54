// Anchor translation unit so the runtime library exists before its first stage lands.
namespace orthosim::runtime {
const char* runtime_name() { return "orthosim_runtime"; }
}  // namespace orthosim::runtime
