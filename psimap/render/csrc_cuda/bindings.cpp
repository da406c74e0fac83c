// torch bindings of the CUDA forward blend (blend_fwd.cu): check the tensors, allocate the
// outputs on the inputs' device and launch on torch's current stream.
#include <torch/extension.h>

#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>

#include <string>
#include <vector>

#include "blend.h"

namespace {

void check_tensor(const torch::Tensor& t, const char* name, torch::ScalarType dtype,
                  const torch::Device& device) {
  TORCH_CHECK(t.device() == device, "blend_forward: ", name, " is on ", t.device(), ", not ", device);
  TORCH_CHECK(t.scalar_type() == dtype, "blend_forward: ", name, " must be ", dtype, ", got ",
              t.scalar_type());
  TORCH_CHECK(t.is_contiguous(), "blend_forward: ", name, " must be contiguous");
}

void check_rows(const torch::Tensor& t, const char* name, int64_t n, std::vector<int64_t> tail) {
  std::vector<int64_t> want{n};
  want.insert(want.end(), tail.begin(), tail.end());
  TORCH_CHECK(t.sizes().vec() == want, "blend_forward: ", name, " has shape ", t.sizes(),
              ", expected ", c10::IntArrayRef(want));
}

// Returns rgb [H, W, 3], alpha [H, W], depth [H, W], median [H, W], normal [H, W, 3],
// distortion [H, W], features [H, W, C], evaluated [1] int64.
std::vector<torch::Tensor> blend_forward(torch::Tensor offsets, torch::Tensor surfel_ids,
                                         torch::Tensor boxes, int64_t tiles_x, int64_t tiles_y, int64_t width,
                                         int64_t height, torch::Tensor T, torch::Tensor center,
                                         torch::Tensor depth_key, torch::Tensor normal_c,
                                         torch::Tensor opacities, torch::Tensor colors,
                                         torch::Tensor features, int64_t topk, double near_plane,
                                         double far_plane, std::vector<double> background) {
  TORCH_CHECK(T.is_cuda(), "blend_forward: the tensors must be on a CUDA device");
  const auto device = T.device();
  const c10::cuda::CUDAGuard guard(device);
  const int64_t n = T.size(0);
  check_tensor(offsets, "offsets", torch::kInt32, device);
  check_tensor(surfel_ids, "surfel_ids", torch::kInt32, device);
  check_tensor(boxes, "boxes", torch::kInt32, device);
  check_rows(boxes, "boxes", n, {4});
  for (auto [t, name] : {std::pair{&T, "T"}, {&center, "center"}, {&depth_key, "depth_key"},
                         {&normal_c, "normal_c"}, {&opacities, "opacities"}, {&colors, "colors"},
                         {&features, "features"}})
    check_tensor(*t, name, torch::kFloat32, device);
  check_rows(T, "T", n, {3, 3});
  check_rows(center, "center", n, {2});
  check_rows(depth_key, "depth_key", n, {});
  check_rows(normal_c, "normal_c", n, {3});
  check_rows(opacities, "opacities", n, {});
  check_rows(colors, "colors", n, {3});
  TORCH_CHECK(features.dim() == 2 && features.size(0) == n, "blend_forward: features must be [N, C]");
  TORCH_CHECK(tiles_x == (width + 15) / 16 && tiles_y == (height + 15) / 16,
              "blend_forward: tile grid does not match the image");
  TORCH_CHECK(offsets.dim() == 1 && offsets.size(0) == tiles_x * tiles_y + 1,
              "blend_forward: offsets must be [tiles + 1]");
  TORCH_CHECK(background.size() == 3, "blend_forward: background must hold 3 values");
  const int64_t C = features.size(1);
  TORCH_CHECK(psimap_cuda::blend_forward_supported(static_cast<int>(C), static_cast<int>(topk)),
              "blend_forward: C = ", C, " with topk = ", topk, " is beyond the CUDA kernel (C <= ",
              psimap_cuda::kMaxChannelsAll, " when blending all, topk <= ", psimap_cuda::kMaxTopK, ")");

  const auto fopt = T.options();
  auto rgb = torch::empty({height, width, 3}, fopt);
  auto alpha = torch::empty({height, width}, fopt);
  auto depth = torch::empty({height, width}, fopt);
  auto median = torch::empty({height, width}, fopt);
  auto normal = torch::empty({height, width, 3}, fopt);
  auto distortion = torch::empty({height, width}, fopt);
  auto out_features = torch::empty({height, width, C}, fopt);
  auto evaluated = torch::zeros({1}, fopt.dtype(torch::kInt64));

  psimap_cuda::BlendForwardArgs a{};
  a.offsets = offsets.data_ptr<int32_t>();
  a.surfel_ids = surfel_ids.data_ptr<int32_t>();
  a.boxes = boxes.data_ptr<int32_t>();
  a.tiles_x = static_cast<int>(tiles_x);
  a.tiles_y = static_cast<int>(tiles_y);
  a.width = static_cast<int>(width);
  a.height = static_cast<int>(height);
  a.T = T.data_ptr<float>();
  a.center = center.data_ptr<float>();
  a.depth_key = depth_key.data_ptr<float>();
  a.normal_c = normal_c.data_ptr<float>();
  a.opacities = opacities.data_ptr<float>();
  a.colors = colors.data_ptr<float>();
  a.features = C ? features.data_ptr<float>() : nullptr;
  a.channels = static_cast<int>(C);
  a.topk = static_cast<int>(topk);
  a.near_plane = static_cast<float>(near_plane);
  a.far_plane = static_cast<float>(far_plane);
  a.bg_r = static_cast<float>(background[0]);
  a.bg_g = static_cast<float>(background[1]);
  a.bg_b = static_cast<float>(background[2]);
  a.rgb = rgb.data_ptr<float>();
  a.alpha = alpha.data_ptr<float>();
  a.depth = depth.data_ptr<float>();
  a.median = median.data_ptr<float>();
  a.normal = normal.data_ptr<float>();
  a.distortion = distortion.data_ptr<float>();
  a.out_features = out_features.data_ptr<float>();
  a.evaluated = reinterpret_cast<unsigned long long*>(evaluated.data_ptr<int64_t>());
  const char* err = psimap_cuda::launch_blend_forward(a, c10::cuda::getCurrentCUDAStream().stream());
  TORCH_CHECK(err == nullptr, "blend_forward: CUDA launch failed: ", err ? err : "");
  return {rgb, alpha, depth, median, normal, distortion, out_features, evaluated};
}

}  // namespace

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("blend_forward", &blend_forward, "Stage 3 forward of SPEC.md on a CUDA device (no gradients)");
  m.def("supported", &psimap_cuda::blend_forward_supported,
        "Whether the kernel holds C channels with this topk (0 = all) in registers");
}
