#include "vtkSIPMSSCommunicator.h"

#include "vtkCommunicator.h"
#include "vtkMultiProcessController.h"

#include <stdexcept>
#include <string>

namespace
{
void Check(int ok, const char* what)
{
  if (!ok)
  {
    throw std::runtime_error(std::string("the MPI controller failed in ") + what);
  }
}
}

vtkSIPMSSCommunicator::vtkSIPMSSCommunicator(vtkMultiProcessController* controller)
  : Controller(controller)
{
}

int vtkSIPMSSCommunicator::Rank() const
{
  return this->Controller->GetLocalProcessId();
}

int vtkSIPMSSCommunicator::Size() const
{
  return this->Controller->GetNumberOfProcesses();
}

void vtkSIPMSSCommunicator::AllReduceMin(double* values, std::size_t n)
{
  std::vector<double> in(values, values + n);
  Check(this->Controller->AllReduce(in.data(), values, vtkIdType(n), vtkCommunicator::MIN_OP),
    "a reduction");
}

void vtkSIPMSSCommunicator::AllReduceMax(double* values, std::size_t n)
{
  std::vector<double> in(values, values + n);
  Check(this->Controller->AllReduce(in.data(), values, vtkIdType(n), vtkCommunicator::MAX_OP),
    "a reduction");
}

void vtkSIPMSSCommunicator::AllReduceSum(std::uint64_t* values, std::size_t n)
{
  std::vector<unsigned long long> in(values, values + n), out(n);
  Check(this->Controller->AllReduce(in.data(), out.data(), vtkIdType(n), vtkCommunicator::SUM_OP),
    "a reduction");
  for (std::size_t i = 0; i < n; ++i)
  {
    values[i] = out[i];
  }
}

void vtkSIPMSSCommunicator::Exchange(const std::vector<std::vector<std::uint8_t>>& send,
  std::vector<std::vector<std::uint8_t>>& received)
{
  const int n = this->Size();
  const int me = this->Rank();
  // sizes[from * n + to]
  std::vector<long long> mine(static_cast<std::size_t>(n), 0),
    sizes(static_cast<std::size_t>(n) * static_cast<std::size_t>(n), 0);
  for (int r = 0; r < n; ++r)
  {
    mine[std::size_t(r)] = static_cast<long long>(send[std::size_t(r)].size());
  }
  Check(this->Controller->AllGather(mine.data(), sizes.data(), vtkIdType(n)), "an all-gather");
  received.assign(std::size_t(n), std::vector<std::uint8_t>{});
  std::vector<vtkIdType> lengths(static_cast<std::size_t>(n)), offsets(static_cast<std::size_t>(n));
  std::vector<char> buffer;
  for (int root = 0; root < n; ++root)
  {
    vtkIdType total = 0;
    for (int from = 0; from < n; ++from)
    {
      lengths[std::size_t(from)] = vtkIdType(sizes[std::size_t(from) * n + root]);
      offsets[std::size_t(from)] = total;
      total += lengths[std::size_t(from)];
    }
    if (total == 0)
    {
      continue; // (every rank knows: nothing goes to root)
    }
    const std::vector<std::uint8_t>& out = send[std::size_t(root)];
    static const char empty = 0;
    const char* data = out.empty() ? &empty : reinterpret_cast<const char*>(out.data());
    if (root == me)
    {
      buffer.resize(std::size_t(total));
      Check(this->Controller->GatherV(data, buffer.data(), vtkIdType(out.size()), lengths.data(),
              offsets.data(), root),
        "a gather");
      for (int from = 0; from < n; ++from)
      {
        const char* at = buffer.data() + offsets[std::size_t(from)];
        received[std::size_t(from)].assign(at, at + lengths[std::size_t(from)]);
      }
    }
    else
    {
      Check(this->Controller->GatherV(data, nullptr, vtkIdType(out.size()), lengths.data(),
              offsets.data(), root),
        "a gather");
    }
  }
}
