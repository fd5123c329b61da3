/* A tiny test runner: CHECK records a failure and carries on; RUN_TEST prints one line per test. */
#ifndef CLOTHD_FW_CHECK_H
#define CLOTHD_FW_CHECK_H

#include <stdio.h>

extern int check_failures;
extern int check_count;

#define CHECK(cond)                                                                                        \
    do {                                                                                                   \
        check_count++;                                                                                     \
        if (!(cond)) {                                                                                     \
            check_failures++;                                                                              \
            printf("  FAIL %s:%d: %s\n", __FILE__, __LINE__, #cond);                              \
        }                                                                                                  \
    } while (0)

#define CHECK_NEAR(actual, expected, tolerance)                                                            \
    do {                                                                                                   \
        double check_a_ = (double)(actual), check_e_ = (double)(expected);                                 \
        double check_d_ = check_a_ > check_e_ ? check_a_ - check_e_ : check_e_ - check_a_;                 \
        check_count++;                                                                                     \
        if (!(check_d_ <= (double)(tolerance))) {                                                          \
            check_failures++;                                                                              \
            printf("  FAIL %s:%d: %s = %g, expected %g +- %g\n", __FILE__, __LINE__, #actual,     \
                    check_a_, check_e_, (double)(tolerance));                                              \
        }                                                                                                  \
    } while (0)

typedef void (*test_fn)(void);

void run_test(const char *name, test_fn fn);

#define RUN_TEST(fn) run_test(#fn, fn)

#endif
