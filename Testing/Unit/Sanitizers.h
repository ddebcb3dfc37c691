// Whether this test is built with a sanitizer (scripts/sanitize), for the tests that measure the
// process's memory or time, or replace the heap: SIPMSS_ADDRESS_SANITIZER and
// SIPMSS_THREAD_SANITIZER, 1 or 0 (GCC defines __SANITIZE_*__, clang has __has_feature).
#pragma once

#if defined(__SANITIZE_ADDRESS__)
#define SIPMSS_ADDRESS_SANITIZER 1
#elif defined(__has_feature)
#if __has_feature(address_sanitizer)
#define SIPMSS_ADDRESS_SANITIZER 1
#endif
#endif
#ifndef SIPMSS_ADDRESS_SANITIZER
#define SIPMSS_ADDRESS_SANITIZER 0
#endif

#if defined(__SANITIZE_THREAD__)
#define SIPMSS_THREAD_SANITIZER 1
#elif defined(__has_feature)
#if __has_feature(thread_sanitizer)
#define SIPMSS_THREAD_SANITIZER 1
#endif
#endif
#ifndef SIPMSS_THREAD_SANITIZER
#define SIPMSS_THREAD_SANITIZER 0
#endif
